"""Frame-by-frame matching of the larynx kernel (the paper's tau_bar(j) = argmax_x [k * N_j](x) - tau0).

Each frame's search window and the kernel's template go through the same band-pass
(``motion.track.kernel.bandpass``); ``cv2.matchTemplate`` TM_CCORR_NORMED (the band-passed values have
no mean left to remove) over the three channels, each kernel pixel weighted by the match window
(``match_window``), within a search band of +-``band_rows`` rows and +-``band_cols`` columns around the
predicted position (the whole frame on the first frame without an initial position, and again after
``reacquire_after`` rejected frames); sub-pixel peak by a 2-D quadratic on the 3x3 scores around the
maximum.  confidence = the peak's weighted normalised correlation (clipped to [0, 1]).  A match below
``min_confidence``, further than ``max_jump_px`` (times the frames since the last accepted one) from
the prediction, or lying on the band's border (the true peak may be beyond it) is rejected: the frame
keeps the last accepted position and gets confidence 0.

With a neck model (``motion.track.neck``) each frame first measures the neck's own displacement at the
larynx; the tracker keeps the larynx's position relative to the neck (its slide) and predicts the next
frame's position as the last slide moved on at the slide's own velocity plus the neck's displacement
in the new frame, so the band follows the head and the jaw rather than extrapolating them.  Without
one, the prediction is the last accepted position moved on by one frame of its velocity (not further
while frames are rejected).

Optional smoothing (``smooth_frames`` > 0): a Gaussian of that sigma in frames, each frame weighted by
its confidence (rejected frames are then filled from their neighbours).
"""
from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import cv2
import numpy as np
from scipy.ndimage import gaussian_filter1d

from base.errors import InputError
from base.progress import progress_bar
from motion.track.config import TrackerConfig
from motion.track.kernel import LarynxKernel, bandpass, bandpass_margins, match_window
from motion.track.neck import NeckModel, NeckPatches
from motion.track.scores import subpixel_peak


@dataclass
class Match:
    """One frame's result: (x, y) pixels, peak NCC, accepted or held, the neck's displacement (dx, dy)
    at the larynx relative to the first frame (NaN without a neck model)."""

    x: float
    y: float
    score: float
    accepted: bool
    neck: tuple[float, float] = (math.nan, math.nan)


class LarynxTracker:
    """Frame-by-frame matcher of a LarynxKernel (see the module doc).

    ``LarynxTracker(kernel, config=None, init=(x, y) or None, neck=NeckModel or None)``;
    ``update(normals [H,W,3] float32) -> Match``.
    """

    def __init__(self, kernel: LarynxKernel, config: TrackerConfig | None = None,
                 init: tuple[float, float] | None = None, neck: NeckModel | None = None):
        self.kernel = kernel
        self.config = config or TrackerConfig()
        self.template = kernel.template(self.config.bandpass)
        self.weights = match_window(kernel, self.config.window)
        self.neck_model = neck
        self.patches: NeckPatches | None = None
        self.init = init
        self.neck = np.zeros(2)         # the neck's displacement at the larynx in the current frame
        self.neck_band = np.zeros(2)    # ... from the neck's patches alone (without the jaw's): the band follows it
        self.jaw_share = np.zeros(2)    # what the jaw's patch adds to it, as last seen
        self.slide = None               # last accepted position (minus the neck's displacement then, if followed)
        self.velocity = (0.0, 0.0)      # px per frame of the slide between the last two accepted positions
        self.missed = 0                 # frames since the last accepted one
        self.origin_y = 0.0             # the larynx's row where the patches were taken (rise 0)

    def _offset(self) -> np.ndarray:
        """What the tracking state is relative to: the neck's vertical displacement when the band follows it
        (the larynx slides vertically; sideways it moves with the neck, at its own constant velocity)."""
        return np.array([0.0, self.neck_band[1]]) if self.config.neck.follow else np.zeros(2)

    @property
    def last(self) -> tuple[float, float] | None:
        """The last accepted position, moved with the neck into the current frame (None before the first)."""
        if self.slide is None:
            return None
        offset = self._offset()
        return self.slide[0] + offset[0], self.slide[1] + offset[1]

    def search(self, normals: np.ndarray, around: tuple[float, float] | None) -> tuple[float, float, float, bool]:
        """Best (x, y, score, inside) within the band around ``around`` (the whole frame if None); ``inside``
        is False when the best score lies on the band's border (the true peak may lie beyond it)."""
        search = self.config.search
        kw, kh = self.kernel.size
        h, w = normals.shape[:2]
        cx, cy = self.kernel.centre
        if around is None:
            x0, y0, x1, y1 = 0, 0, w - kw, h - kh
        else:
            # Top-left corners of the kernel whose centre lies within the band.
            tx, ty = int(round(around[0] - cx)), int(round(around[1] - cy))
            x0, x1 = max(0, tx - search.band_cols), min(w - kw, tx + search.band_cols)
            y0, y1 = max(0, ty - search.band_rows), min(h - kh, ty + search.band_rows)
            if x1 < x0 or y1 < y0:
                return float("nan"), float("nan"), -1.0, False
        # Band-pass the window with the context the filters need, so it holds what filtering the whole
        # frame would give there.
        margin_rows, margin_cols = bandpass_margins(self.config.bandpass)
        ya, yb = max(0, y0 - margin_rows), min(h, y1 + kh + margin_rows)
        xa, xb = max(0, x0 - margin_cols), min(w, x1 + kw + margin_cols)
        region = bandpass(normals[ya:yb, xa:xb], self.config.bandpass)
        window = np.ascontiguousarray(region[y0 - ya:y1 + kh - ya, x0 - xa:x1 + kw - xa])
        scores = cv2.matchTemplate(window, self.template, cv2.TM_CCORR_NORMED, mask=self.weights)
        _, peak, _, (col, row) = cv2.minMaxLoc(scores)
        rows, cols = scores.shape
        inside = (0 < row < rows - 1 or rows == 1) and (0 < col < cols - 1 or cols == 1)
        if search.subpixel:
            px, py = subpixel_peak(scores, col, row)
        else:
            px, py = float(col), float(row)
        return x0 + px + cx, y0 + py + cy, float(peak), inside

    def prediction(self) -> tuple[float, float] | None:
        """Where the larynx should be in the current frame: the last slide moved on by one frame of its
        velocity, plus the neck's displacement in this frame (with ``neck.follow`` off or without a neck
        model: the last position moved on by one frame of its velocity); None before the first position.
        The velocity is not extrapolated through rejected frames: at the top of a swallow, where the
        larynx turns under the jaw and its matches are rejected, a band run on at the rise's velocity
        left the larynx behind (at 0.16 cm/px it then locked onto the chin; issue 46)."""
        if self.slide is None:
            return None
        offset = self._offset()
        return (self.slide[0] + self.velocity[0] + offset[0], self.slide[1] + self.velocity[1] + offset[1])

    def _start_patches(self, normals: np.ndarray, at: tuple[float, float]) -> None:
        """Take the neck's patches around the larynx position ``at`` of this frame (the neck's origin)."""
        if self.neck_model is not None:
            self.patches = NeckPatches(normals, at, self.neck_model.offsets, self.config.neck, self.neck_model.free)
            self.neck = np.zeros(2)
            self.neck_band = np.zeros(2)
            self.origin_y = float(at[1])

    def _measure_neck(self, normals: np.ndarray) -> None:
        """The neck's displacement in this frame (held when no patch matches)."""
        if self.patches is None:
            return
        displacements, present = self.patches.measure(normals)
        rise = 0.0
        if self.slide is not None:
            relative_y = self.slide[1] + self._offset()[1] - self.neck[1]       # last position relative to the neck
            rise = self.origin_y - relative_y
        neck_only = present & ~self.patches.free[:, None]
        if neck_only[:, 1].sum() >= self.config.neck.min_patches:    # else held: too few to trust
            self.neck_band = self.neck_model.displacement(displacements, neck_only, rise)
            if present[self.patches.free].any():          # the jaw's share: what its patch adds to the neck's
                self.jaw_share = self.neck_model.displacement(displacements, present, rise) - self.neck_band
            # Without the jaw's patch in this frame its share is held: the jaw is taken not to have moved.
            self.neck = self.neck_band + self.jaw_share

    def _neck_out(self) -> tuple[float, float]:
        return (float(self.neck[0]), float(self.neck[1])) if self.patches is not None else (math.nan, math.nan)

    def update(self, normals: np.ndarray) -> Match:
        cfg = self.config.search
        if self.slide is None and self.init is not None:          # the first frame, at a given position
            self.slide = (float(self.init[0]), float(self.init[1]))
            self._start_patches(normals, self.slide)
            self.init = None
        else:
            self._measure_neck(normals)
        reacquire = self.slide is None or self.missed >= cfg.reacquire_after
        predicted = self.prediction()
        x, y, score, inside = self.search(normals, None if reacquire else predicted)
        ok = inside and score >= cfg.min_confidence
        if ok and not reacquire:
            ok = math.hypot(x - predicted[0], y - predicted[1]) <= cfg.max_jump_px * (self.missed + 1)
        if ok:
            if self.patches is None:                              # the first position found: the neck's origin
                self._start_patches(normals, (x, y))
            offset = self._offset()
            slide = (x - offset[0], y - offset[1])
            if self.slide is not None and not reacquire:
                steps = self.missed + 1
                self.velocity = ((slide[0] - self.slide[0]) / steps, (slide[1] - self.slide[1]) / steps)
            else:
                self.velocity = (0.0, 0.0)
            self.slide, self.missed = slide, 0
            return Match(x, y, score, True, self._neck_out())
        self.missed += 1
        held = self.last if self.slide is not None else (float("nan"), float("nan"))
        return Match(held[0], held[1], score, False, self._neck_out())


@dataclass
class Track:
    """Per-frame results: x, y [T] pixels, confidence [T] (0 where rejected), accepted [T] bool, neck
    [T,2] the neck's displacement at the larynx relative to the first frame (NaN without a neck model)."""

    x: np.ndarray
    y: np.ndarray
    confidence: np.ndarray
    accepted: np.ndarray
    neck: np.ndarray

    def __len__(self) -> int:
        return len(self.x)


def smooth_track(track: Track, sigma_frames: float) -> Track:
    """Confidence-weighted Gaussian smoothing of x and y (normalised convolution); rejected frames
    (confidence 0) take their neighbours' values.  ``sigma_frames`` 0: the track itself."""
    if sigma_frames <= 0:
        return track
    weights = np.where(np.isfinite(track.x), track.confidence, 0.0).astype(np.float64)
    den = gaussian_filter1d(weights, sigma_frames, mode="constant", truncate=3.0)

    def smooth(values: np.ndarray) -> np.ndarray:
        num = gaussian_filter1d(np.nan_to_num(values) * weights, sigma_frames, mode="constant", truncate=3.0)
        return np.where(den > 1e-9, num / np.maximum(den, 1e-9), values)

    return Track(smooth(track.x), smooth(track.y), track.confidence, track.accepted, track.neck)


def track_sequence(frames: Iterable[np.ndarray], kernel: LarynxKernel, config: TrackerConfig | None = None,
                   init: tuple[float, float] | None = None, neck: NeckModel | None = None,
                   progress: bool = False, total: int | None = None) -> Track:
    """Track the larynx through a sequence.

    Args:
        frames: decoded normal maps [H,W,3] float32 (``motion.track.sources``), in order.
        kernel: the larynx kernel (``motion.track.kernel``), at the frames' pixel scale.
        config: the tracker's settings (default ``TrackerConfig()``), at the frames' pixel scale.
        init: the larynx's (x, y) in the first frame; None searches the whole first frame.
        neck: the neck model (``NeckModel.from_rig``) whose motion the band follows and the track reports.
        progress: show a progress bar (``total`` frames).
    Returns:
        the Track [T] (smoothed per ``config.smooth_frames``); InputError without frames.
    """
    tracker = LarynxTracker(kernel, config, init, neck)
    matches = []
    iterator = frames
    if progress:
        iterator = progress_bar(frames, total=total, unit="frame", desc="tracking")
    for normals in iterator:
        matches.append(tracker.update(normals))
    if not matches:
        raise InputError("no frames to track")
    track = Track(np.array([m.x for m in matches]), np.array([m.y for m in matches]),
                  np.array([np.clip(m.score, 0.0, 1.0) if m.accepted else 0.0 for m in matches]),
                  np.array([m.accepted for m in matches]), np.array([m.neck for m in matches], dtype=np.float64))
    return smooth_track(track, tracker.config.smooth_frames)
