"""The capture's pixel scale (cm per pixel at the neck) read from its normal maps, when it is not given.

The rig at rest in the default neck view, rendered at ``WORK_CM_PER_PX`` and band-passed like the
tracker's frames (``motion.track.kernel.bandpass``, its settings scaled to that resolution), gives a
template of the neck around the larynx point: ``SCALE_TEMPLATE_PX`` (the larynx with the neck's relief
beside and below it; what the jaw reaches above it is left out).  A frame at an unknown scale c is
resampled by c / ``WORK_CM_PER_PX`` (to the template's resolution if c is right), band-passed, and matched
against the template over the whole frame (``cv2.matchTemplate`` TM_CCORR_NORMED); the peak correlation,
averaged over frames, is largest where c is the capture's scale.  Search: a coarse grid in steps of
2^(1/4) over the scales in ``SCALE_RANGE_CM_PER_PX`` at which the resampled frame holds the template and
the frame spans at most ``MAX_VIEW_CM`` (scored on the first ``COARSE_FRAMES`` sampled frames), then steps
of 2^(1/32) within one coarse step of the best (on every sampled frame: every ``FRAME_STEP``-th of the
first ``ESTIMATE_FRAMES``), and a parabola through the best three in log scale.

Why this template: the tracker's own kernel (the larynx's normal perturbation alone) peaks 9-11 % too
coarse even on frames of the rig at rest (the neck's relief around the larynx correlates with it at a
slightly wrong scale); the neck's view as the frames show it is exact at rest.  Head motion and the jaw
move the estimate: on the real rig's talking-and-moving sequences -2.0 to +2.1 % (``benchmarks/README.md``,
section "Tracker and renderer").  The rig's neck stands for the subject's: a neck wider or narrower than
the rig's around the larynx reads as a finer or coarser scale.

:func:`estimate_scale` estimates; :func:`check_scale` compares a given scale with the estimate and words
the warning when they differ by more than ``DISAGREEMENT``.
"""
from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

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
SCALE_RANGE_CM_PER_PX = (0.005, 0.64)   # the scales searched (a neck 25 to 1,600 px wide)
WORK_CM_PER_PX = 0.16                  # frames are matched at this scale (0.08 and 0.12: errors within 1 % of
                                       # these, 2-4 times the time)
MAX_VIEW_CM = 60.0                     # a frame spanning more than this is taken to be at a finer scale
ESTIMATE_FRAMES = 90                   # the first frames the estimate looks at (3 s at 30 fps) ...
FRAME_STEP = 6                         # ... every 6th of them
COARSE_FRAMES = 3                      # sampled frames the coarse search scores
COARSE_STEP = 2.0 ** 0.25
FINE_STEP = 2.0 ** (1 / 32)
MIN_SCORE = 0.5                        # below this mean peak correlation the frames do not look like the rig's neck
                                       # (the real rig's talking sequences: 0.86-0.94 at their scale)
DISAGREEMENT = 0.15                    # a given scale further than this from the frames' is warned about


@dataclass
class ScaleEstimate:
    """cm_per_px the estimated scale; score the mean peak correlation there; frames the frames it used."""

    cm_per_px: float
    score: float
    frames: int


def _work_bandpass(config: BandpassConfig | None) -> BandpassConfig:
    """The band-pass (pixels at 0.08 cm/px) in pixels of ``WORK_CM_PER_PX``."""
    return (config or BandpassConfig()).at_scale(DEFAULT_CM_PER_PX / WORK_CM_PER_PX)


def scale_template(rig, config: BandpassConfig | None = None) -> np.ndarray:
    """The band-passed rest view of ``rig`` around the larynx point [h,w,3] at ``WORK_CM_PER_PX``
    (``SCALE_TEMPLATE_PX``); ``config``: the band-pass in pixels at 0.08 cm/px."""
    factor = DEFAULT_CM_PER_PX / WORK_CM_PER_PX
    kernel = rig_kernel(rig, WORK_CM_PER_PX, max(5, round(KERNEL_SIZE * factor)), round(CONTEXT_MARGIN * factor))
    view = bandpass(kernel.context, _work_bandpass(config))
    cx, cy = (round(o + c) for o, c in zip(kernel.offset, kernel.centre))
    left, right, top, bottom = (round(v * factor) for v in SCALE_TEMPLATE_PX)
    if cy + top < 0 or cx + left < 0 or cy + bottom > view.shape[0] or cx + right > view.shape[1]:
        raise ValueError("SCALE_TEMPLATE_PX reaches beyond the rig kernel's context")
    return np.ascontiguousarray(view[cy + top:cy + bottom, cx + left:cx + right])


def sample_frames(frames) -> list[np.ndarray]:
    """Every ``FRAME_STEP``-th of the first ``ESTIMATE_FRAMES`` decoded frames of an iterable."""
    sampled = []
    for i, frame in enumerate(frames):
        if i >= ESTIMATE_FRAMES:
            break
        if i % FRAME_STEP == 0:
            sampled.append(np.asarray(frame, dtype=np.float32))
    return sampled


def _valid(cm_per_px: float, shape: tuple[int, ...], template: np.ndarray) -> bool:
    """Whether a frame of ``shape`` at ``cm_per_px``, resampled to ``WORK_CM_PER_PX``, holds the template and spans
    at most ``MAX_VIEW_CM``."""
    h, w = shape[:2]
    factor = cm_per_px / WORK_CM_PER_PX
    low, high = SCALE_RANGE_CM_PER_PX
    return (low <= cm_per_px <= high and max(h, w) * cm_per_px <= MAX_VIEW_CM
            and round(h * factor) >= template.shape[0] and round(w * factor) >= template.shape[1])


def peak_scores(frames: Sequence[np.ndarray], template: np.ndarray, candidates: np.ndarray,
                config: BandpassConfig | None = None) -> np.ndarray:
    """The template's peak normalised correlation [F,C] in each frame resampled as if at each candidate scale
    (cm/px); NaN where the candidate is not searchable (see the module doc)."""
    config = _work_bandpass(config)
    scores = np.full((len(frames), len(candidates)), np.nan)
    for j, cm_per_px in enumerate(candidates):
        factor = cm_per_px / WORK_CM_PER_PX
        for i, frame in enumerate(frames):
            if not _valid(cm_per_px, frame.shape, template):
                continue
            h, w = frame.shape[:2]
            size = (round(w * factor), round(h * factor))
            image = cv2.resize(frame, size, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR)
            match = cv2.matchTemplate(bandpass(image, config), template, cv2.TM_CCORR_NORMED)
            scores[i, j] = float(np.nan_to_num(match, nan=-1.0, posinf=-1.0, neginf=-1.0).max())
    return scores


def _mean_curve(scores: np.ndarray) -> np.ndarray:
    """The mean over frames [C] of peak scores [F,C], NaN where no frame was scored."""
    finite = np.isfinite(scores)
    count = finite.sum(axis=0)
    return np.where(count > 0, np.where(finite, scores, 0.0).sum(axis=0) / np.maximum(count, 1), np.nan)


def _refine(candidates: np.ndarray, curve: np.ndarray) -> float:
    """The scale at the parabola's vertex through the best score and its neighbours (log scale)."""
    best = int(np.nanargmax(curve))
    if 0 < best < len(curve) - 1 and np.isfinite(curve[best - 1:best + 2]).all():
        x = np.log(candidates[best - 1:best + 2])
        a, b, _ = np.polyfit(x - x[1], curve[best - 1:best + 2], 2)
        if a < 0:
            return float(candidates[best] * math.exp(float(np.clip(-b / (2 * a), x[0] - x[1], x[2] - x[1]))))
    return float(candidates[best])


def _fine(frames: Sequence[np.ndarray], template: np.ndarray, centre: float, reach: float,
          config: BandpassConfig | None) -> tuple[float, float]:
    """(scale, mean peak score) of the fine search within a factor ``reach`` of ``centre``."""
    steps = int(round(math.log(reach) / math.log(FINE_STEP)))
    candidates = centre * FINE_STEP ** np.arange(-steps, steps + 1)
    curve = _mean_curve(peak_scores(frames, template, candidates, config))
    if not np.isfinite(curve).any():
        return math.nan, math.nan
    return _refine(candidates, curve), float(np.nanmax(curve))


def estimate_scale(frames: Sequence[np.ndarray], rig, config: BandpassConfig | None = None,
                   template: np.ndarray | None = None) -> ScaleEstimate:
    """The frames' pixel scale (cm/px at the neck) from their match with the rig's neck (see the module doc).

    Args:
        frames: decoded normal maps [H,W,3] (``sample_frames`` of a sequence's first frames).
        rig: a ``models.rig.HeadNeckModel``, the neck the frames are compared with.
        config: the band-pass, pixels at 0.08 cm/px (default ``BandpassConfig()``).
        template: ``scale_template(rig, config)``, when already made.
    Returns:
        the estimate; InputError when no scale in ``SCALE_RANGE_CM_PER_PX`` fits the frames or none
        matches the rig's neck (peak correlation below ``MIN_SCORE``).
    """
    if not len(frames):
        raise InputError("no frames to estimate the pixel scale from")
    template = scale_template(rig, config) if template is None else template
    low, high = SCALE_RANGE_CM_PER_PX
    steps = np.arange(math.floor(math.log(low / DEFAULT_CM_PER_PX, COARSE_STEP)),
                      math.ceil(math.log(high / DEFAULT_CM_PER_PX, COARSE_STEP)) + 1)
    coarse = DEFAULT_CM_PER_PX * COARSE_STEP ** steps
    coarse = coarse[[_valid(c, frames[0].shape, template) for c in coarse]]
    h, w = frames[0].shape[:2]
    if not len(coarse):
        raise InputError(f"{w}x{h} frames are too small to estimate their pixel scale; give cm_per_px=")
    curve = _mean_curve(peak_scores(frames[:COARSE_FRAMES], template, coarse, config))
    scale, score = _fine(frames, template, float(coarse[int(np.nanargmax(curve))]), COARSE_STEP, config)
    if not np.isfinite(score) or score < MIN_SCORE:
        raise InputError(f"the frames do not match the rig's neck at any scale (best correlation {score:.2f}, "
                         f"expected at least {MIN_SCORE}); give cm_per_px= (the capture's pixel scale at the neck)")
    return ScaleEstimate(scale, score, len(frames))


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
