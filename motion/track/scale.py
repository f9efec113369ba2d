"""The capture's pixel scale (cm per pixel at the neck) read from its normal maps, when it is not given.

The rig at rest in the default neck view, rendered at a matching scale (``WORK_CM_PER_PX``) and band-passed like
the tracker's frames (``motion.track.kernel.bandpass``, its settings scaled to that resolution, the column high-
pass and the low-pass capped: ``SCALE_COLUMN_HIGHPASS_PX``, ``SCALE_LOWPASS_SIGMA_PX``), gives a template of the
neck around the larynx point: ``SCALE_TEMPLATE_PX`` (the larynx with the neck's relief beside and below it; what
the jaw reaches above it is left out). A frame at an unknown scale c is resampled by c / work (to the template's
resolution if c is right), band-passed, and matched against the template over their overlap
(:func:`overlap_peak`): the normalised correlation over the part of the template the frame shows, so that a
frame framed wider than the template (the whole head) holds all of it and a close-up (a neck filling the frame:
chin, larynx, lower neck) is matched by the part it shows. The peak correlation is largest where c is the
capture's scale. Search: a coarse grid in steps of 2^(1/4) over the scales in
``SCALE_RANGE_CM_PER_PX`` at which the frame shows between ``MIN_VIEW_CM`` (its short side) and ``MAX_VIEW_CM``
(its long side), at 0.16 cm/px, on the first ``COARSE_FRAMES`` sampled frames; then steps of 2^(1/32) within
``FINE_REACH`` of the coarse curve's parabola vertex, on every sampled frame (every ``FRAME_STEP``-th of the
first ``ESTIMATE_FRAMES``) cut to the template's extent and ``CROP_MARGIN_CM`` around the coarse match, at the
coarsest matching scale at which the cut spans ``MIN_WORK_PX`` (0.08 cm/px for views under 10 cm); each frame's
scale at the parabola's vertex through its best three (log scale); the estimate the median of those over the
``REST_SHARE`` of the frames whose peak correlation is highest.

Why the frames that match best: the jaw opening and the head's flexion make a frame's own scale read coarser
(real rig, 6.4 cm of neck, 15 frames of a talking sequence: within 1.3 % where the jaw is shut and the head
near upright, peak correlation 0.94-0.96, +5 to +12 % with the jaw open 0.2-0.4 and 2-4 degrees of flexion,
0.83-0.91), and a swallow's top (tau 0.075) reads -23 % (0.59) on the real rig and +8 % (0.97) on the built-in
one.  The mean correlation curve over all frames read +4.3 % there; the median of the best half's own scales
+1.7 %.  Over 56 other sequences (seeds 1-3, three recordings, noise 0.05-0.08 and blur, the real rig reshaped
into another person, seven framings): worst error 3.5 % (3.3 % built-in, 2.6 % reshaped) against 7.8 % with
the mean curve; the best third: the same worst errors (``benchmarks/README.md``).

Why the frame's borders weigh less (``BORDER_CM``): the band-pass reflects a frame at its edges where the
template saw the neck beyond; on 6.4 cm of the real rig's neck at rest that read 2.4 % too coarse (+0.6 %
band-passed with the neck around it), +1.3 % with the borders weighted down (``benchmarks/README.md``).  The
column high-pass capped at 4.9 cm (the tracker's is 8 cm) for the same reason: close-ups at 30 and 40 px/cm
+2.8 / +4.5 % with 8 cm, +1.4 / +2.8 % with 4.9 cm (3.3 cm: +2.0 / +3.4 %).  The low-pass capped at 0.24 cm
(the tracker's 0.32): on 90-frame talking sequences at the sweep's twelve framings the real rig's errors span
+0.3 to +2.9 % with 0.32 cm, +0.6 to +1.9 % with 0.24, -0.7 to +2.2 % with 0.16; the built-in rig's -1.3 to
+2.0, -1.8 to +0.8 and -3.1 to -0.4 %.

Why this template: the tracker's own kernel (the larynx's normal perturbation alone) peaks 9-11 % too
coarse even on frames of the rig at rest (the neck's relief around the larynx correlates with it at a
slightly wrong scale); the neck's view as the frames show it is exact at rest.  Head motion and the jaw
move the estimate (``benchmarks/README.md``, section "Tracker and renderer", framing sweep).  The rig's neck
stands for the subject's: a neck wider or narrower than the rig's around the larynx reads as a finer or
coarser scale.

When it cannot decide (no scale matches at ``MIN_SCORE``, or a second peak of the coarse curve, two steps or
more from the best, comes within ``AMBIGUITY`` of it) the error names every scale compared and its score.

:func:`estimate_scale` estimates; :func:`check_scale` compares a given scale with the estimate and words
the warning when they differ by more than ``DISAGREEMENT``.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from base.errors import InputError
from motion.track.config import BandpassConfig
from motion.track.kernel import CONTEXT_MARGIN, KERNEL_SIZE, bandpass, rig_kernel
from scene.render import DEFAULT_CM_PER_PX

# The template's extent around the rest larynx point in pixels at 0.08 cm/px: (left, right, top, bottom), x
# right, y down.  Wider and lower than the larynx kernel: the neck beside and below the larynx holds its shape
# while the jaw moves (real rig, five talking sequences: 110 x 80 px errs -0.6 to +2.4 %, 70 x 70 px -0.1 to +3.3 %).
SCALE_TEMPLATE_PX = (-55, 55, -30, 50)
SCALE_COLUMN_HIGHPASS_PX = 61           # the column high-pass (px at 0.08 cm/px) is capped at 4.9 cm: see the doc
SCALE_LOWPASS_SIGMA_PX = 3.0            # the low-pass sigma (px at 0.08 cm/px) is capped at 0.24 cm: see the doc
SCALE_RANGE_CM_PER_PX = (0.005, 0.64)   # the scales searched (a neck 25 to 1,600 px wide)
WORK_CM_PER_PX = (0.16, 0.08, 0.04)     # matching scales: the coarse search at the first, the fine one at the
MIN_WORK_PX = 64                        # coarsest at which the region searched spans this many pixels
MIN_VIEW_CM = 4.8                       # a frame showing less than this (its short side) is not scored
MAX_VIEW_CM = 100.0                     # a frame spanning more than this is taken to be at a finer scale
MIN_OVERLAP = 0.75                      # of the frame's or the template's side, whichever is shorter
BORDER_CM = 1.5                         # a frame's pixels nearer its edge than this weigh less (``border_weight``)
CROP_MARGIN_CM = 4.0                    # the fine search looks this far around the coarse search's match
ESTIMATE_FRAMES = 90                    # the first frames the estimate looks at (3 s at 30 fps) ...
FRAME_STEP = 6                          # ... every 6th of them
REST_SHARE = 0.5                        # the fine search's scale: the median of the frames' own, over the half
                                        # of the frames that match the rig's rest view best (see the doc)
COARSE_FRAMES = 3                       # sampled frames the coarse search scores
COARSE_STEP = 2.0 ** 0.25
FINE_STEP = 2.0 ** (1 / 32)
FINE_REACH = 2.0 ** (1 / 8)              # the fine search's reach around the coarse curve's vertex
MIN_SCORE = 0.5                         # below this mean peak correlation the frames do not look like the rig's neck
                                        # (the real rig's talking sequences: 0.82-0.94 at their scale)
AMBIGUITY = 0.03                        # a second coarse peak this close to the best leaves the scale undecided
                                        # (framing sweep: the best scale leads any other peak by 0.13 or more)
DISAGREEMENT = 0.15                     # a given scale further than this from the frames' is warned about


@dataclass
class ScaleEstimate:
    """cm_per_px the estimated scale; score the mean peak correlation there; frames the frames it used;
    compared the coarse search's (cm_per_px, mean peak correlation) pairs."""

    cm_per_px: float
    score: float
    frames: int
    compared: list[tuple[float, float]] = field(default_factory=list)


def _work_bandpass(config: BandpassConfig | None, work: float) -> BandpassConfig:
    """The band-pass (pixels at 0.08 cm/px, column high-pass and low-pass capped at ``SCALE_COLUMN_HIGHPASS_PX``
    and ``SCALE_LOWPASS_SIGMA_PX``) in pixels of ``work`` cm/px."""
    config = config or BandpassConfig()
    config = replace(config, column_highpass_px=min(config.column_highpass_px, SCALE_COLUMN_HIGHPASS_PX),
                     lowpass_sigma_px=min(config.lowpass_sigma_px, SCALE_LOWPASS_SIGMA_PX))
    return config.at_scale(DEFAULT_CM_PER_PX / work)


def scale_template(rig, config: BandpassConfig | None = None, work: float = WORK_CM_PER_PX[0]) -> np.ndarray:
    """The band-passed rest view of ``rig`` around the larynx point [h,w,3] at ``work`` cm/px
    (``SCALE_TEMPLATE_PX``); ``config``: the band-pass in pixels at 0.08 cm/px."""
    factor = DEFAULT_CM_PER_PX / work
    kernel = rig_kernel(rig, work, max(5, round(KERNEL_SIZE * factor)), round(CONTEXT_MARGIN * factor))
    view = bandpass(kernel.context, _work_bandpass(config, work))
    cx, cy = (round(o + c) for o, c in zip(kernel.offset, kernel.centre))
    left, right, top, bottom = (round(v * factor) for v in SCALE_TEMPLATE_PX)
    if cy + top < 0 or cx + left < 0 or cy + bottom > view.shape[0] or cx + right > view.shape[1]:
        raise ValueError("SCALE_TEMPLATE_PX reaches beyond the rig kernel's context")
    return np.ascontiguousarray(view[cy + top:cy + bottom, cx + left:cx + right])


class Templates(dict):
    """``scale_template`` of one rig and band-pass per matching scale, made when first asked for."""

    def __init__(self, rig, config: BandpassConfig | None = None):
        super().__init__()
        self.rig, self.config = rig, config

    def __missing__(self, work: float) -> np.ndarray:
        self[work] = scale_template(self.rig, self.config, work)
        return self[work]


def sample_frames(frames) -> list[np.ndarray]:
    """Every ``FRAME_STEP``-th of the first ``ESTIMATE_FRAMES`` decoded frames of an iterable."""
    sampled = []
    for i, frame in enumerate(frames):
        if i >= ESTIMATE_FRAMES:
            break
        if i % FRAME_STEP == 0:
            sampled.append(np.asarray(frame, dtype=np.float32))
    return sampled


def _valid(cm_per_px: float, shape: tuple[int, ...]) -> bool:
    """Whether a frame of ``shape`` at ``cm_per_px`` is scored: its short side shows at least ``MIN_VIEW_CM``,
    its long side at most ``MAX_VIEW_CM``."""
    h, w = shape[:2]
    low, high = SCALE_RANGE_CM_PER_PX
    return low <= cm_per_px <= high and min(h, w) * cm_per_px >= MIN_VIEW_CM and max(h, w) * cm_per_px <= MAX_VIEW_CM


def _box_sums(table: np.ndarray, y0, y1, x0, x1) -> np.ndarray:
    return table[y1, x1] - table[y0, x1] - table[y1, x0] + table[y0, x0]


def border_weight(shape: tuple[int, ...], reach: float) -> np.ndarray:
    """[h,w] float32: 1 further than ``reach`` px from the frame's edges, falling linearly to 0 at them (where the
    band-pass reflects the frame instead of seeing the neck beyond it)."""
    h, w = shape[:2]
    rows = np.minimum(np.arange(h) + 0.5, h - 0.5 - np.arange(h))
    cols = np.minimum(np.arange(w) + 0.5, w - 0.5 - np.arange(w))
    return np.minimum(1.0, np.minimum(rows[:, None], cols[None, :]) / max(reach, 1e-6)).astype(np.float32)


def overlap_peak(image: np.ndarray, template: np.ndarray, weight: np.ndarray) -> tuple[float, int, int]:
    """(score, row, col) of the template's best placement in a band-passed image [h,w,3] weighted by ``weight``
    [h,w]: the normalised correlation sum(w f t) / sqrt(sum(w f^2) sum(w t^2)) over the part of the template
    that overlaps the image, at placements that overlap at least ``MIN_OVERLAP`` of the shorter side in each
    direction and where the image's band holds at least 5 % of the template's energy there (not background);
    row, col the template's top-left (may be negative).  A template larger than the image is thus matched by
    the part of it the image shows."""
    h, w = image.shape[:2]
    th, tw = template.shape[:2]
    py, px = th - math.ceil(MIN_OVERLAP * min(h, th)), tw - math.ceil(MIN_OVERLAP * min(w, tw))
    weighted = image * weight[..., None]
    products = cv2.matchTemplate(cv2.copyMakeBorder(weighted, py, py, px, px, cv2.BORDER_CONSTANT, value=0),
                                 template, cv2.TM_CCORR).astype(np.float64)
    template_energy = cv2.matchTemplate(cv2.copyMakeBorder(weight, py, py, px, px, cv2.BORDER_CONSTANT, value=0),
                                        np.einsum("hwc,hwc->hw", template, template), cv2.TM_CCORR).astype(np.float64)
    rows = np.arange(products.shape[0])[:, None] - py
    cols = np.arange(products.shape[1])[None, :] - px
    y0, y1, x0, x1 = np.clip(rows, 0, h), np.clip(rows + th, 0, h), np.clip(cols, 0, w), np.clip(cols + tw, 0, w)
    image_energy = _box_sums(cv2.integral(np.einsum("hwc,hwc->hw", weighted, image).astype(np.float64)),
                             y0, y1, x0, x1)
    scores = np.where(image_energy > 0.05 * template_energy,
                      products / np.sqrt(np.maximum(image_energy * template_energy, 1e-12)), -1.0)
    best = int(np.argmax(scores))
    row, col = divmod(best, scores.shape[1])
    return float(scores[row, col]), row - py, col - px


def peak_scores(frames: Sequence[np.ndarray], template: np.ndarray, candidates: np.ndarray, work: float,
                config: BandpassConfig | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(scores [F,C], positions [F,C,2]): the template's peak correlation (``overlap_peak``) in each frame
    resampled from each candidate scale (cm/px) to ``work`` cm/px, NaN where the candidate is not searchable
    (``_valid``), and the template's larynx point there (x, y) in frame pixels."""
    config = _work_bandpass(config, work)
    scores = np.full((len(frames), len(candidates)), np.nan)
    positions = np.full((len(frames), len(candidates), 2), np.nan)
    left, _, top, _ = (v * DEFAULT_CM_PER_PX / work for v in SCALE_TEMPLATE_PX)
    weight = None
    for j, cm_per_px in enumerate(candidates):
        factor = cm_per_px / work
        for i, frame in enumerate(frames):
            if not _valid(cm_per_px, frame.shape):
                continue
            h, w = frame.shape[:2]
            size = (max(1, round(w * factor)), max(1, round(h * factor)))
            image = cv2.resize(frame, size, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR)
            if weight is None or weight.shape != image.shape[:2]:
                weight = border_weight(image.shape, BORDER_CM / work)
            scores[i, j], row, col = overlap_peak(bandpass(image, config), template, weight)
            positions[i, j] = ((col - left) / factor, (row - top) / factor)
    return scores, positions


def _mean_curve(scores: np.ndarray) -> np.ndarray:
    """The mean over frames [C] of peak scores [F,C], NaN where no frame was scored."""
    finite = np.isfinite(scores)
    count = finite.sum(axis=0)
    return np.where(count > 0, np.where(finite, scores, 0.0).sum(axis=0) / np.maximum(count, 1), np.nan)


def _most_at_rest(scores: np.ndarray) -> np.ndarray:
    """The rows of peak scores [F,C] (a row scored somewhere) of the ``REST_SHARE`` of frames whose best score
    is highest, in frame order."""
    best = np.where(np.isfinite(scores), scores, -np.inf).max(axis=1)
    scored = np.flatnonzero(np.isfinite(best))
    keep = max(1, math.ceil(REST_SHARE * len(scored)))
    return scores[np.sort(scored[np.argsort(-best[scored], kind="stable")[:keep]])]


def _refine(candidates: np.ndarray, curve: np.ndarray) -> float:
    """The scale at the parabola's vertex through the best score and its neighbours (log scale)."""
    best = int(np.nanargmax(curve))
    if 0 < best < len(curve) - 1 and np.isfinite(curve[best - 1:best + 2]).all():
        x = np.log(candidates[best - 1:best + 2])
        a, b, _ = np.polyfit(x - x[1], curve[best - 1:best + 2], 2)
        if a < 0:
            return float(candidates[best] * math.exp(float(np.clip(-b / (2 * a), x[0] - x[1], x[2] - x[1]))))
    return float(candidates[best])


def _crop(frames: Sequence[np.ndarray], centre: np.ndarray, cm_per_px: float) -> list[np.ndarray]:
    """The frames cut to the template's extent around ``centre`` (x, y frame pixels, the larynx point the coarse
    search found at ``cm_per_px``) and ``CROP_MARGIN_CM`` beyond, at scales up to ``FINE_REACH`` finer."""
    left, right, top, bottom = (v * DEFAULT_CM_PER_PX for v in SCALE_TEMPLATE_PX)
    reach = FINE_REACH / cm_per_px
    h, w = frames[0].shape[:2]
    x0, x1 = (int(np.clip(round(centre[0] + v * reach), 0, w)) for v in (left - CROP_MARGIN_CM, right + CROP_MARGIN_CM))
    y0, y1 = (int(np.clip(round(centre[1] + v * reach), 0, h)) for v in (top - CROP_MARGIN_CM, bottom + CROP_MARGIN_CM))
    return [np.ascontiguousarray(frame[y0:y1, x0:x1]) for frame in frames]


def _fine(frames: Sequence[np.ndarray], templates: Templates, centre: float, position: np.ndarray,
          config: BandpassConfig | None) -> tuple[float, float]:
    """(scale, mean peak score) of the fine search within a factor ``FINE_REACH`` of ``centre``, on the frames
    cut around ``position`` (``_crop``), at the coarsest matching scale at which the cut spans ``MIN_WORK_PX``."""
    steps = int(round(math.log(FINE_REACH) / math.log(FINE_STEP)))
    candidates = centre * FINE_STEP ** np.arange(-steps, steps + 1)
    valid = [_valid(c, frames[0].shape) for c in candidates]
    if not any(valid):
        return math.nan, math.nan
    cut = _crop(frames, position, centre)
    short = min(cut[0].shape[:2]) * candidates[valid].min()
    work = next((v for v in WORK_CM_PER_PX if short / v >= MIN_WORK_PX), WORK_CM_PER_PX[-1])
    scores, _ = peak_scores(cut, templates[work], candidates, work, config)
    # the crop changes nothing but the frames' size: which candidates are searchable follows the whole frame
    scores[:, ~np.asarray(valid)] = np.nan
    kept = _most_at_rest(scores)
    per_frame = np.log([_refine(candidates, row) for row in kept])
    return float(np.exp(np.median(per_frame))), float(np.mean(np.nanmax(kept, axis=1)))


def _listing(compared: Sequence[tuple[float, float]]) -> str:
    return ", ".join(f"{c:.4g}: {s:.2f}" for c, s in compared)


def estimate_scale(frames: Sequence[np.ndarray], rig, config: BandpassConfig | None = None,
                   templates: Templates | None = None) -> ScaleEstimate:
    """The frames' pixel scale (cm/px at the neck) from their match with the rig's neck (see the module doc).

    Args:
        frames: decoded normal maps [H,W,3] (``sample_frames`` of a sequence's first frames).
        rig: a ``models.rig.HeadNeckModel``, the neck the frames are compared with.
        config: the band-pass, pixels at 0.08 cm/px (default ``BandpassConfig()``).
        templates: ``Templates(rig, config)``, when already made.
    Returns:
        the estimate; InputError when no scale in ``SCALE_RANGE_CM_PER_PX`` fits the frames or none
        matches the rig's neck (peak correlation below ``MIN_SCORE``), naming the scales compared and their
        scores.
    """
    if not len(frames):
        raise InputError("no frames to estimate the pixel scale from")
    templates = Templates(rig, config) if templates is None else templates
    low, high = SCALE_RANGE_CM_PER_PX
    steps = np.arange(math.floor(math.log(low / DEFAULT_CM_PER_PX, COARSE_STEP)),
                      math.ceil(math.log(high / DEFAULT_CM_PER_PX, COARSE_STEP)) + 1)
    coarse = DEFAULT_CM_PER_PX * COARSE_STEP ** steps
    coarse = coarse[[_valid(c, frames[0].shape) for c in coarse]]
    h, w = frames[0].shape[:2]
    if not len(coarse):
        raise InputError(f"{w}x{h} frames are too small to estimate their pixel scale (they would show at least "
                         f"{MIN_VIEW_CM:g} cm at {high:g} cm/px); give cm_per_px=")
    work = WORK_CM_PER_PX[0]
    scores, positions = peak_scores(frames[:COARSE_FRAMES], templates[work], coarse, work, config)
    curve = _mean_curve(scores)
    compared = [(float(c), float(s)) for c, s in zip(coarse, curve)]
    best = int(np.nanargmax(curve))
    scale, score = _fine(frames, templates, _refine(coarse, curve), np.nanmedian(positions[:, best], axis=0), config)
    if not np.isfinite(score) or score < MIN_SCORE:
        raise InputError(f"the frames do not match the rig's neck at any scale (best correlation {score:.2f} near "
                         f"{coarse[best]:.4g} cm/px, expected at least {MIN_SCORE}; mean peak correlation at each "
                         f"scale compared, cm/px: {_listing(compared)}); give cm_per_px= (the capture's pixel scale "
                         f"at the neck)")
    rival = _rival(curve, best)
    if rival is not None:
        raise InputError(f"the frames match the rig's neck about as well at {coarse[rival]:.4g} cm/px as at "
                         f"{coarse[best]:.4g} (mean peak correlation {curve[rival]:.2f} and {curve[best]:.2f}; mean "
                         f"peak correlation at each scale compared, cm/px: {_listing(compared)}); give cm_per_px= "
                         f"(the capture's pixel scale at the neck)")
    return ScaleEstimate(scale, score, len(frames), compared)


def _rival(curve: np.ndarray, best: int) -> int | None:
    """The index of the coarse curve's best local maximum two steps or more from ``best`` scoring within
    ``AMBIGUITY`` of it, else None."""
    values = np.where(np.isfinite(curve), curve, -np.inf)
    peaks = [i for i in range(len(values)) if abs(i - best) >= 2 and np.isfinite(values[i])
             and (i == 0 or values[i] > values[i - 1]) and (i == len(values) - 1 or values[i] > values[i + 1])]
    rival = max(peaks, key=lambda i: values[i], default=None)
    return rival if rival is not None and values[rival] >= values[best] - AMBIGUITY else None


def check_scale(frames: Sequence[np.ndarray], rig, cm_per_px: float, config: BandpassConfig | None = None,
                tolerance: float = DISAGREEMENT) -> str | None:
    """A one-line warning when the given ``cm_per_px`` and the frames' own scale differ by more than
    ``tolerance`` (relative), else None (also when the frames do not match the rig's neck at any scale:
    the given scale is then all there is)."""
    try:
        scale = estimate_scale(frames, rig, config).cm_per_px
    except InputError:
        return None
    if abs(scale / cm_per_px - 1) <= tolerance:
        return None
    return (f"warning: cm_per_px={cm_per_px:g} disagrees with the images by {100 * (cm_per_px / scale - 1):+.0f}%: "
            f"they match the rig's neck at {scale:.4g} cm/px; check the scale, or leave cm_per_px out to use "
            f"the estimate")
