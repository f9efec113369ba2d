"""Swallow template: detect swallows in tau tracks, register them by their landmarks, average, play back.

The paper's swallowing control curve is the average of several captured
swallows aligned in time by their peaks and valleys; the curve then drives the
larynx slide ``tau`` of any HACK character (``HeadNeckModel(...)(theta,
tau=...)``).  This module builds that curve and inserts it into tau tracks.

Conventions (tau units and sign: ``data.tau_track``; shape: ``data.synthetic_tau``):

- A swallow has up to five landmarks, in this order: ``onset`` (leaves rest),
  ``dip`` (small preparatory valley below rest before the rise), ``peak``
  (highest elevation), ``undershoot`` (valley below rest after the peak) and
  ``return`` (back at rest).  Peaks are found with ``scipy.signal.find_peaks``
  (prominence, width, height, separation) on a smoothed signal; dip and
  undershoot are the lowest points beyond the peak's flanks, kept if they go
  below the rest band ``max(rest_fraction * height, noise_factor * noise)``,
  with sub-frame (parabolic) refinement.  Onset and return are tangent
  intercepts with rest of the steepest flank between the valley (or peak) and
  the point where the signal re-enters the rest band (``rest_point=band``: that
  crossing itself); as the curve leaves and reaches rest with zero slope they
  lie slightly inside the true span, consistently for every swallow.
- Levels are measured from a rest baseline estimated from the track's rest
  samples (a running median), so offsets and slow drift do not enter the
  template.  The template is the displacement from rest: 0 at rest.
- Template time 0 is the onset; the template carries ``pad_seconds`` of rest
  before the onset (negative times) and after the return.
- Registration: each swallow gets an increasing time warp (piecewise linear or
  PCHIP) mapping the mean landmark times to its own landmark times (slope 1
  outside them); it is resampled through the warp on a uniform grid at
  ``template_fps`` and the aligned swallows are averaged (mean and per-time
  standard deviation).  Landmark registration: Ramsay & Silverman, Functional
  Data Analysis, 2nd ed., 2005, ch. 7.

CLI (hydra, ``configs/swallow.yaml``)::

    python -m motion.swallow inputs=[a.csv,b.csv] out=template.csv [plot=template.png]
    python -m motion.swallow mode=play track=in.csv template=template.csv at=[2.0,7.5] out=out.csv \\
        [duration_scale=1.2] [amplitude_scale=0.8] [plot=play.png]

Inputs are tau tracks (``data.tau_track.read_tau_track``: CSV with ``tau`` and
``time`` or ``frame`` [+ ``fps``], or ``.npy``); ``fps=...`` is the frame rate
of files that carry none (``.npy``, a CSV with ``frame`` but no ``time`` or
``fps`` column).  Tracker CSVs (``python -m motion.track``) lose the rows below
``min_confidence`` (lost and rejected frames; the track is resampled over the
gap).  ``inputs`` and ``at`` take one value or a list (``inputs=a.csv``,
``at=2.0``).  A template file is what :func:`write_template` writes.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
from omegaconf import DictConfig
from scipy.interpolate import PchipInterpolator
from scipy.ndimage import gaussian_filter1d, median_filter
from scipy.signal import find_peaks

from data.cli import config_dataclass, run_cli
from data.cli import as_list
from data.errors import InputError
from data.files import write_csv
from data.plots import figure, save_figure
from data.tables import CsvTable
from data.tau_track import TauTrack, read_tau_track, write_tau_track
from data.timebase import check_increasing, estimate_fps, resample_uniform
from motion.signal import parabolic_peak

LANDMARK_NAMES: tuple[str, ...] = ("onset", "dip", "peak", "undershoot", "return")
ONSET, DIP, PEAK, UNDERSHOOT, RETURN = range(5)
REQUIRED_LANDMARKS = (ONSET, PEAK, RETURN)
OPTIONAL_LANDMARKS = (DIP, UNDERSHOOT)


@dataclass
class SwallowConfig:
    """Thresholds of detection, registration and playback (mirrored by ``configs/swallow.yaml: swallow``).

    Seconds are track time; tau values in tau units (0.03 ~ 1 cm).  Defaults
    suit human swallows: the larynx rises 1.5-2.5 cm and returns within about a
    second (see ``data.synthetic_tau``), so the rise is a bump of about 0.3 s
    width at half prominence, while speech wobble is 2-6 Hz.
    """

    # detection
    smooth_seconds: float = 0.02          # Gaussian sigma of the signal landmarks are read from
    detect_smooth_seconds: float = 0.08   # Gaussian sigma for finding peaks (damps 2-6 Hz speech)
    baseline_seconds: float = 4.0         # running-median window of the rest baseline
    min_prominence: float = 0.02          # tau units (~0.7 cm): scipy.signal.find_peaks prominence
    min_height: float = 0.015             # tau units above the rest baseline
    min_width_seconds: float = 0.1        # peak width at half prominence
    max_width_seconds: float = 1.0
    min_separation_seconds: float = 0.8   # between two swallows' peaks
    rest_fraction: float = 0.04           # rest band = max(rest_fraction * height, noise_factor * noise)
    noise_factor: float = 2.0
    rest_point: str = "tangent"           # onset/return: tangent (tangent-intercept) | band (band crossing)
    valley_window_seconds: float = 0.5    # how far beyond the rising/falling flank a dip/undershoot is sought
    max_rest_search_seconds: float = 1.0  # how far beyond a valley the onset/return is sought
    refine_seconds: float = 0.08          # extrema are refined on the fine signal within this distance
    # registration
    template_fps: float = 60.0
    warp: str = "linear"                  # linear | pchip
    pad_seconds: float = 0.3              # rest kept before the onset and after the return
    landmark_majority: float = 0.5        # optional landmarks (dip, undershoot) used if this share of swallows has them
    max_duration_ratio: float = 2.0       # swallows longer/shorter than this factor of the median are rejected
    max_height_ratio: float = 2.5         # same for peak heights
    min_swallows: int = 1
    # playback
    fade_seconds: float = 0.2             # (> 0) raised-cosine cross-fade at both ends of an inserted swallow
    rest_window_seconds: float = 0.5      # track rest level is the median over this window before/after an insert
    blend: str = "replace"                # replace: cross-fade to rest + template; add: add the template

    def __post_init__(self) -> None:
        if self.warp not in ("linear", "pchip"):
            raise ValueError(f"SwallowConfig.warp must be 'linear' or 'pchip', got '{self.warp}'")
        if self.rest_point not in ("tangent", "band"):
            raise ValueError(f"SwallowConfig.rest_point must be 'tangent' or 'band', got '{self.rest_point}'")
        if self.blend not in ("replace", "add"):
            raise ValueError(f"SwallowConfig.blend must be 'replace' or 'add', got '{self.blend}'")
        for key in ("template_fps", "fade_seconds"):
            if not getattr(self, key) > 0:
                raise ValueError(f"SwallowConfig.{key} (swallow.{key}) must be positive, got {getattr(self, key)}")


# --------------------------------------------------------------------------- detection


@dataclass
class SwallowEvent:
    """One swallow in a track.

    times:  [5] seconds (track time) of onset, dip, peak, undershoot, return; NaN where missing.
    levels: [5] tau above the rest baseline at those times; NaN where missing.
    height: peak tau above the baseline; prominence: scipy prominence on the detection signal.
    missing: landmark name -> why it is missing.
    """

    times: np.ndarray
    levels: np.ndarray
    height: float
    prominence: float
    missing: dict[str, str] = field(default_factory=dict)

    @property
    def complete(self) -> bool:
        """Onset, peak and return found (the minimum for registration)."""
        return bool(np.isfinite(self.times[list(REQUIRED_LANDMARKS)]).all())

    @property
    def duration(self) -> float:
        return float(self.times[RETURN] - self.times[ONSET])

    def has(self, landmark: int) -> bool:
        return bool(np.isfinite(self.times[landmark]))

    def reason(self) -> str:
        return "; ".join(f"{name}: {why}" for name, why in self.missing.items())


@dataclass
class TrackAnalysis:
    """Swallows of one uniformly sampled track and its rest baseline.

    events: swallows in time order; baseline [T] rest level (tau); noise: robust
    std of the fine signal about the detection signal; note: why no swallow was found.
    """

    events: list[SwallowEvent]
    baseline: np.ndarray
    noise: float
    note: str = ""


def _smooth(x: np.ndarray, sigma_samples: float) -> np.ndarray:
    return gaussian_filter1d(x, sigma_samples, mode="nearest") if sigma_samples > 0.3 else x.copy()


def _refine_extremum(x: np.ndarray, i: int) -> tuple[float, float]:
    """Sub-sample position and value of an extremum at sample ``i`` by a parabola through 3 samples."""
    if 0 < i < len(x) - 1:
        offset, value = parabolic_peak(x[i - 1], x[i], x[i + 1])
        return i + offset, value
    return float(i), float(x[i])


def _walk_to_rest(signal: np.ndarray, start: int, stop: int, band: float) -> float | None:
    """From ``start`` towards ``stop`` (inclusive), the sub-sample position where |signal| first enters ``band``."""
    step = 1 if stop >= start else -1
    previous = start
    for i in range(start + step, stop + step, step):
        if abs(signal[i]) <= band:
            a, b = abs(signal[previous]), abs(signal[i])
            fraction = (a - band) / (a - b) if a != b else 1.0
            return previous + step * float(np.clip(fraction, 0.0, 1.0))
        previous = i
    return None


def _first_below(signal: np.ndarray, start: int, stop: int, level: float) -> int:
    """First index from ``start`` towards ``stop`` (inclusive) where ``signal < level``; ``stop`` if none."""
    step = 1 if stop >= start else -1
    segment = signal[start:stop + step if stop + step >= 0 else None:step]
    below = np.flatnonzero(segment < level)
    return start + step * int(below[0]) if len(below) else stop


def _tangent_intercept(sig: np.ndarray, slope: np.ndarray, anchor: int, crossing: float) -> float:
    """Where the tangent at the steepest point between ``anchor`` (an extremum) and the rest
    ``crossing`` meets rest (0): the classic tangent-intercept onset, less biased than the band
    crossing for curves that leave rest with zero slope.  Kept within [crossing - |anchor - crossing|,
    crossing] (onsets) or [crossing, crossing + |anchor - crossing|] (returns)."""
    direction = 1 if crossing > anchor else -1
    lo, hi = sorted((anchor, int(np.floor(crossing)) if direction < 0 else int(np.ceil(crossing))))
    hi = min(hi, len(sig) - 1)
    segment = slope[lo:hi + 1]
    if len(segment) == 0:
        return crossing
    toward_rest = -np.sign(sig[anchor]) * direction  # slope sign on the way from the extremum back to rest
    m = lo + int(np.argmax(toward_rest * segment))
    if toward_rest * slope[m] <= 0:
        return crossing
    intercept = m - sig[m] / slope[m]
    reach = abs(anchor - crossing)
    if direction < 0:
        return float(np.clip(intercept, crossing - reach, crossing))
    return float(np.clip(intercept, crossing, crossing + reach))


def _find_events(fine: np.ndarray, coarse: np.ndarray, baseline: np.ndarray, fps: float, noise: float,
                 cfg: SwallowConfig) -> list[SwallowEvent]:
    """Swallows in a track; ``fine``/``coarse`` are the lightly/strongly smoothed signals [T]."""
    n = len(fine)
    detect = coarse - baseline
    sig = fine - baseline
    slope = np.gradient(sig)
    peaks, props = find_peaks(
        detect, height=cfg.min_height, prominence=cfg.min_prominence,
        width=(cfg.min_width_seconds * fps, cfg.max_width_seconds * fps),
        distance=max(1.0, cfg.min_separation_seconds * fps),
    )
    refine = max(1, int(round(cfg.refine_seconds * fps)))
    valley_window = max(1, int(round(cfg.valley_window_seconds * fps)))
    rest_search = max(1, int(round(cfg.max_rest_search_seconds * fps)))
    events = []
    for k, p in enumerate(peaks):
        left = int(peaks[k - 1]) if k > 0 else 0
        right = int(peaks[k + 1]) if k + 1 < len(peaks) else n - 1
        lo, hi = max(left, p - refine), min(right, p + refine)
        i_peak = lo + int(np.argmax(sig[lo:hi + 1]))
        peak_pos, peak_val = _refine_extremum(sig, i_peak)
        height = peak_val
        band = max(cfg.rest_fraction * height, cfg.noise_factor * noise)
        times = np.full(5, np.nan)
        levels = np.full(5, np.nan)
        times[PEAK], levels[PEAK] = peak_pos, peak_val
        missing: dict[str, str] = {}

        def valley(name: str, flank: int, direction: int) -> int | None:
            """Lowest point beyond the flank where the lobe drops below the band; None if not below -band."""
            a, b = sorted((flank, flank + direction * valley_window))
            a, b = max(a, left), min(b, right)
            if b <= a:
                missing[name] = "no room before the neighbouring swallow or the track end"
                return None
            i = a + int(np.argmin(sig[a:b + 1]))
            far_edge = a if direction < 0 else b
            if i == far_edge and far_edge not in (0, n - 1):
                missing[name] = "no valley: the signal keeps falling to the end of the search window"
                return None
            if sig[i] >= -band:
                missing[name] = (f"no valley below rest (lowest {sig[i] / height:+.2f} of the peak height, "
                                 f"band {band / height:.2f})")
                return None
            pos, val = _refine_extremum(sig, i)
            index = LANDMARK_NAMES.index(name)
            times[index], levels[index] = pos, val
            return i

        # The lobe's flanks: the first samples below the band before and after the peak.
        dip_i = valley("dip", _first_below(sig, i_peak, left, band), -1)
        under_i = valley("undershoot", _first_below(sig, i_peak, right, band), +1)

        for index, anchor, direction, after in ((ONSET, dip_i, -1, "dip"), (RETURN, under_i, +1, "undershoot")):
            if anchor is None:
                anchor, after = i_peak, "peak"
            stop = max(left, anchor - rest_search, 0) if direction < 0 else min(right, anchor + rest_search, n - 1)
            crossing = _walk_to_rest(sig, anchor, stop, band)
            if crossing is None:
                where = "track start or previous swallow" if direction < 0 else "track end or next swallow"
                missing[LANDMARK_NAMES[index]] = (f"no rest within {cfg.max_rest_search_seconds:g} s "
                                                  f"{'before' if direction < 0 else 'after'} the {after} ({where})")
                continue
            position = _tangent_intercept(sig, slope, anchor, crossing) if cfg.rest_point == "tangent" else crossing
            times[index], levels[index] = position, float(np.interp(position, np.arange(n), sig))
        events.append(SwallowEvent(times / fps, levels, float(height), float(props["prominences"][k]), missing))
    return events


def _rest_baseline(coarse: np.ndarray, rest: np.ndarray, fps: float, cfg: SwallowConfig) -> np.ndarray:
    """Running median of the rest samples, interpolated across the swallows."""
    index = np.arange(len(coarse))
    if rest.sum() < max(3, 0.05 * len(coarse)):
        return np.full(len(coarse), float(np.median(coarse[rest])) if rest.any() else float(np.median(coarse)))
    window = max(1, int(round(cfg.baseline_seconds * fps)) | 1)
    level = median_filter(coarse[rest], size=window, mode="nearest")
    return np.interp(index, index[rest], level)


def analyse_track(tau: np.ndarray, fps: float, config: SwallowConfig | None = None,
                  start_time: float = 0.0) -> TrackAnalysis:
    """Detect swallows in a uniformly sampled tau track [T] at ``fps``; times are ``start_time`` + index / fps.

    Two passes: a running-median baseline over everything, then a baseline from
    the rest samples only (outside the swallows found), with which the
    landmarks are found again.
    """
    cfg = config or SwallowConfig()
    tau = np.asarray(tau, dtype=np.float64)
    if tau.ndim != 1 or len(tau) < 5:
        raise ValueError(f"analyse_track: expected a tau track [T] with T >= 5, got shape {tau.shape}")
    fine = _smooth(tau, cfg.smooth_seconds * fps)
    coarse = _smooth(tau, cfg.detect_smooth_seconds * fps)
    residual = fine - coarse
    noise = float(1.4826 * np.median(np.abs(residual - np.median(residual))))
    window = max(1, int(round(cfg.baseline_seconds * fps)) | 1)
    baseline = median_filter(coarse, size=window, mode="nearest")
    events = _find_events(fine, coarse, baseline, fps, noise, cfg)
    if events:
        rest = np.ones(len(tau), dtype=bool)
        margin = 0.1  # seconds of the track kept out of the rest baseline around each swallow
        for e in events:
            start = e.times[ONSET] if e.has(ONSET) else e.times[PEAK] - cfg.max_rest_search_seconds
            stop = e.times[RETURN] if e.has(RETURN) else e.times[PEAK] + cfg.max_rest_search_seconds
            rest[max(0, int((start - margin) * fps)):int(np.ceil((stop + margin) * fps)) + 1] = False
        baseline = _rest_baseline(coarse, rest, fps, cfg)
        events = _find_events(fine, coarse, baseline, fps, noise, cfg)
    note = "" if events else _why_no_swallow(coarse - baseline, fps, cfg)
    for e in events:
        e.times = e.times + start_time
    return TrackAnalysis(events, baseline, noise, note)


def _why_no_swallow(detect: np.ndarray, fps: float, cfg: SwallowConfig) -> str:
    peaks, props = find_peaks(detect, prominence=0.0, width=0.0)
    if len(peaks) == 0:
        return "no swallow: the track has no local maximum"
    best = int(np.argmax(props["prominences"]))
    prominence = props["prominences"][best]
    width = props["widths"][best] / fps
    height = detect[peaks[best]]
    if prominence < cfg.min_prominence:
        return (f"no swallow: the largest bump (at {peaks[best] / fps:.2f} s) has prominence {prominence:.4f}, "
                f"below min_prominence {cfg.min_prominence:g}")
    if height < cfg.min_height:
        return f"no swallow: the largest bump rises {height:.4f} above rest, below min_height {cfg.min_height:g}"
    return (f"no swallow: the largest bump (at {peaks[best] / fps:.2f} s, prominence {prominence:.4f}) is "
            f"{width:.2f} s wide, outside [{cfg.min_width_seconds:g}, {cfg.max_width_seconds:g}] s")


def detect_swallows(tau: np.ndarray, fps: float, config: SwallowConfig | None = None,
                    start_time: float = 0.0) -> list[SwallowEvent]:
    """Swallows in a uniformly sampled tau track [T] at ``fps`` (see :func:`analyse_track`)."""
    return analyse_track(tau, fps, config, start_time).events


def uniform_track(track: TauTrack) -> TauTrack:
    """The track itself if uniformly sampled at its fps, else linearly resampled at its fps."""
    steps = np.diff(track.time)
    if len(steps) == 0 or np.allclose(steps, 1.0 / track.fps, rtol=1e-3, atol=1e-6):
        return track
    time, tau = resample_uniform(track.time, track.tau, track.fps)
    return TauTrack(tau, time, track.fps, track.source)


# --------------------------------------------------------------------------- registration


def landmark_warps(grid: np.ndarray, target: np.ndarray, landmarks: np.ndarray, kind: str = "linear") -> np.ndarray:
    """Increasing time warps through landmarks.

    grid [S] template times; target [K] increasing template landmark times;
    landmarks [M,K] increasing landmark times of M curves.  Returns [M,S]: curve
    time for each template time, through (target_k, landmarks_mk), piecewise
    linear (``kind='linear'``) or PCHIP (monotone cubic, ``'pchip'``) between
    the landmarks and with slope 1 beyond them.
    """
    grid = np.asarray(grid, dtype=np.float64)
    target = np.asarray(target, dtype=np.float64)
    landmarks = np.atleast_2d(np.asarray(landmarks, dtype=np.float64))
    out = np.empty((len(landmarks), len(grid)))
    for m, marks in enumerate(landmarks):
        if kind == "pchip" and len(target) > 2:
            inside = PchipInterpolator(target, marks)(np.clip(grid, target[0], target[-1]))
        else:
            inside = np.interp(grid, target, marks)
        out[m] = np.where(grid < target[0], marks[0] + grid - target[0],
                          np.where(grid > target[-1], marks[-1] + grid - target[-1], inside))
    return out


def register_curves(times: Sequence[np.ndarray], values: Sequence[np.ndarray], landmarks: np.ndarray,
                    target: np.ndarray, grid: np.ndarray, kind: str = "linear") -> np.ndarray:
    """Resample M curves through their landmark warps onto a template grid.

    times[m] [T_m], values[m] [T_m]: curve m (any sampling); landmarks [M,K]
    (curve times), target [K] (template times), grid [S].  Returns [M,S]:
    curve m at warp_m(grid); NaN where the warp leaves the curve's time span.
    """
    warps = landmark_warps(grid, target, landmarks, kind)
    return np.stack([np.interp(w, t, v, left=np.nan, right=np.nan) for w, t, v in zip(warps, times, values)])


def nan_mean_std(curves: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Mean, sample std (0 where one value) and count over axis 0 of [M,S], ignoring NaN."""
    count = np.isfinite(curves).sum(axis=0)
    filled = np.where(np.isfinite(curves), curves, 0.0)
    safe = np.maximum(count, 1)
    mean = filled.sum(axis=0) / safe
    square = (np.where(np.isfinite(curves), curves - mean, 0.0) ** 2).sum(axis=0)
    std = np.sqrt(square / np.maximum(count - 1, 1))
    return np.where(count > 0, mean, np.nan), np.where(count > 1, std, 0.0), count


@dataclass
class SwallowTemplate:
    """The swallow control curve.

    time [S] seconds (0 = onset, uniform at ``fps``), tau [S] displacement from
    rest (tau units), std [S] per-time standard deviation of the aligned
    swallows; landmarks [K] template times of ``landmark_names``.
    """

    time: np.ndarray
    tau: np.ndarray
    std: np.ndarray
    fps: float
    landmarks: np.ndarray = None
    landmark_names: tuple[str, ...] = ()

    @property
    def peak_height(self) -> float:
        return float(np.max(self.tau))

    @property
    def duration(self) -> float:
        """Onset to return (s); without landmarks, the span where |tau| exceeds 4% of the peak."""
        if self.landmarks is not None and len(self.landmarks) >= 2:
            return float(self.landmarks[-1] - self.landmarks[0])
        active = np.flatnonzero(np.abs(self.tau) > 0.04 * self.peak_height)
        return float(self.time[active[-1]] - self.time[active[0]]) if len(active) else 0.0

    def __call__(self, time: np.ndarray) -> np.ndarray:
        """Template displacement at template times [...] (PCHIP between samples, 0 outside its span)."""
        time = np.asarray(time, dtype=np.float64)
        inside = (time >= self.time[0]) & (time <= self.time[-1])
        values = PchipInterpolator(self.time, self.tau)(np.clip(time, self.time[0], self.time[-1]))
        return np.where(inside, values, 0.0)


@dataclass
class ClipReport:
    """What happened to one input: swallows found, used, and why others (or the clip) were not used."""

    source: str
    found: int = 0
    used: int = 0
    reasons: list[str] = field(default_factory=list)

    @property
    def is_used(self) -> bool:
        return self.used > 0


@dataclass
class TemplateBuild:
    """Result of :func:`build_template`.

    template; aligned [M,S] the used swallows on the template grid (NaN outside
    their data); naive_time [S'] / naive_tau [S'] the unaligned mean of the used
    clips (baseline removed, time since each clip's start); clips: one report per
    input; events [(clip index, SwallowEvent)] for the M used swallows.
    """

    template: SwallowTemplate
    aligned: np.ndarray
    naive_time: np.ndarray
    naive_tau: np.ndarray
    clips: list[ClipReport]
    events: list[tuple[int, SwallowEvent]]

    def report(self) -> str:
        lines = []
        for c in self.clips:
            if c.is_used:
                lines.append(f"  used     {c.source}: {c.used} of {c.found} swallow(s)")
            else:
                lines.append(f"  rejected {c.source}: {'; '.join(c.reasons)}")
            if c.is_used and c.reasons:
                lines.extend(f"           - {r}" for r in c.reasons)
        t = self.template
        used = sum(c.is_used for c in self.clips)
        marks = ", ".join(f"{n} {v:.3f}" for n, v in zip(t.landmark_names, t.landmarks))
        lines.append(f"template: {len(self.events)} swallow(s) from {used} of {len(self.clips)} clip(s); "
                     f"peak height {t.peak_height:.4f} tau (~{t.peak_height / 0.03:.2f} cm), "
                     f"duration {t.duration:.3f} s (onset to return), {len(t.time)} samples at {t.fps:g} fps")
        lines.append(f"landmarks (s from onset): {marks}")
        return "\n".join(lines)


def build_template(tracks: Sequence[TauTrack], config: SwallowConfig | None = None) -> TemplateBuild:
    """Detect swallows in ``tracks``, select the usable ones, register them and average.

    Every complete swallow (onset, peak and return found) of every track is a
    candidate.  The dip and undershoot are landmarks of the template if at least
    ``landmark_majority`` of the candidates have them; candidates lacking a
    template landmark, or whose duration or height is off the median by more
    than ``max_duration_ratio`` / ``max_height_ratio``, are rejected with the
    reason.  Raises InputError when fewer than ``min_swallows`` remain.
    """
    cfg = config or SwallowConfig()
    reports = [ClipReport(track.source or f"clip {i}") for i, track in enumerate(tracks)]
    uniform = [uniform_track(t) for t in tracks]
    analyses = []
    candidates: list[tuple[int, SwallowEvent]] = []
    for i, track in enumerate(uniform):
        if len(track) < 5:
            reports[i].reasons.append(f"only {len(track)} samples")
            analyses.append(None)
            continue
        analysis = analyse_track(track.tau, track.fps, cfg, start_time=float(track.time[0]))
        analyses.append(analysis)
        reports[i].found = len(analysis.events)
        if not analysis.events:
            reports[i].reasons.append(analysis.note)
        for e in analysis.events:
            if e.complete:
                candidates.append((i, e))
            else:
                reports[i].reasons.append(f"swallow at {e.times[PEAK]:.2f} s incomplete ({e.reason()})")

    # Landmark set: required ones plus optional ones most swallows have.
    used_marks = list(REQUIRED_LANDMARKS)
    for mark in OPTIONAL_LANDMARKS:
        share = np.mean([e.has(mark) for _, e in candidates]) if candidates else 0.0
        if candidates and share >= cfg.landmark_majority:
            used_marks.append(mark)
    used_marks.sort()
    names = tuple(LANDMARK_NAMES[m] for m in used_marks)
    kept = []
    for i, e in candidates:
        lacking = [LANDMARK_NAMES[m] for m in used_marks if not e.has(m)]
        if lacking:
            reports[i].reasons.append(
                f"swallow at {e.times[PEAK]:.2f} s has no {' / '.join(lacking)} "
                f"({'; '.join(e.missing[n] for n in lacking)}); the template uses {', '.join(names)}")
        else:
            kept.append((i, e))
    if kept:
        med_duration = np.median([e.duration for _, e in kept])
        med_height = np.median([e.height for _, e in kept])
        selected = []
        for i, e in kept:
            d, h = e.duration / med_duration, e.height / med_height
            if not 1 / cfg.max_duration_ratio <= d <= cfg.max_duration_ratio:
                reports[i].reasons.append(f"swallow at {e.times[PEAK]:.2f} s lasts {e.duration:.2f} s, {d:.2f}x "
                                          f"the median {med_duration:.2f} s (max_duration_ratio "
                                          f"{cfg.max_duration_ratio:g})")
            elif not 1 / cfg.max_height_ratio <= h <= cfg.max_height_ratio:
                reports[i].reasons.append(f"swallow at {e.times[PEAK]:.2f} s rises {e.height:.4f}, {h:.2f}x "
                                          f"the median {med_height:.4f} (max_height_ratio {cfg.max_height_ratio:g})")
            else:
                selected.append((i, e))
        kept = selected
    if len(kept) < max(1, cfg.min_swallows):
        detail = "\n".join(f"  {r.source}: {'; '.join(r.reasons) or 'ok'}" for r in reports)
        raise InputError(f"{len(kept)} usable swallow(s), need at least {max(1, cfg.min_swallows)}:\n{detail}")
    for i, _ in kept:
        reports[i].used += 1

    marks = np.array([e.times[used_marks] for _, e in kept])        # [M,K]
    target = (marks - marks[:, :1]).mean(axis=0)                     # [K], onset at 0
    step = 1.0 / cfg.template_fps
    first = -int(round(cfg.pad_seconds * cfg.template_fps))
    last = int(np.ceil((target[-1] + cfg.pad_seconds) * cfg.template_fps))
    grid = np.arange(first, last + 1) * step
    times = [uniform[i].time for i, _ in kept]
    values = [uniform[i].tau - analyses[i].baseline for i, _ in kept]
    aligned = register_curves(times, values, marks, target, grid, cfg.warp)
    mean, std, count = nan_mean_std(aligned)
    keep = count > 0
    template = SwallowTemplate(grid[keep], mean[keep], std[keep], cfg.template_fps, target, names)

    clip_ids = sorted({i for i, _ in kept})
    span = min(uniform[i].time[-1] - uniform[i].time[0] for i in clip_ids)
    naive_time = np.arange(int(np.floor(span * cfg.template_fps)) + 1) * step
    naive = np.stack([np.interp(naive_time, uniform[i].time - uniform[i].time[0],
                                uniform[i].tau - analyses[i].baseline) for i in clip_ids])
    return TemplateBuild(template, aligned[:, keep], naive_time, naive.mean(axis=0), reports, kept)


def shift_aligned_error(time: np.ndarray, values: np.ndarray, ref_time: np.ndarray, ref_values: np.ndarray,
                        max_shift: float = 1.0, resolution: float = 0.002) -> tuple[float, float, float]:
    """Error of a curve against a reference after the best time shift.

    time [S], values [S]: the curve (0 outside its span); ref_time [R],
    ref_values [R]: the reference.  Returns (rms, max_abs, shift): RMS and max
    |curve(t - shift) - reference(t)| over the reference's span (a window fixed
    for every curve compared), minimised (RMS) over shifts in [-max_shift,
    max_shift] s; ``shift`` is added to ``time``.  Used to compare templates whose
    time origin is a detected (biased) onset with a known truth.
    """
    grid = np.arange(ref_time[0], ref_time[-1] + resolution / 2, resolution)
    ref = np.interp(grid, ref_time, ref_values)
    best = (np.inf, np.inf, 0.0)
    for s in np.arange(-max_shift, max_shift + resolution / 2, resolution):
        diff = np.interp(grid, time + s, values, left=0.0, right=0.0) - ref
        rms = float(np.sqrt(np.mean(diff ** 2)))
        if rms < best[0]:
            best = (rms, float(np.max(np.abs(diff))), float(s))
    return best


# --------------------------------------------------------------------------- playback


def insert_swallows(tau: np.ndarray, time: np.ndarray, template: SwallowTemplate, at: Sequence[float],
                    duration_scale: float | Sequence[float] = 1.0, amplitude_scale: float | Sequence[float] = 1.0,
                    config: SwallowConfig | None = None) -> np.ndarray:
    """Insert the template into a tau track at onset times ``at`` (seconds).

    tau [..., T] (e.g. [T] from the tracker or a file, [B,T] from the
    transformer), time [T] seconds.  Insert j plays the template stretched by
    ``duration_scale[j]`` in time and ``amplitude_scale[j]`` in height, its
    onset at ``at[j]``.  A weight w rises from 0 to 1 over ``fade_seconds``
    (raised cosine) at the start of the scaled template span and falls back at
    its end (shortened to the template's padding before its onset, if
    shorter).  ``blend='replace'``: out = (1-w) tau + w (rest + template), where
    rest goes linearly from the track's median over ``rest_window_seconds``
    before the insert to that after it (so the track's own motion there is
    cross-faded away); ``blend='add'``: out = tau + w template.  Inserts are
    applied in order; returns [..., T].
    """
    cfg = config or SwallowConfig()
    out = np.array(tau, dtype=np.float64, copy=True)
    time = np.asarray(time, dtype=np.float64)
    if out.shape[-1] != len(time):
        raise ValueError(f"insert_swallows: tau {out.shape} and time {time.shape} disagree on T")
    at = np.atleast_1d(np.asarray(at, dtype=np.float64))
    scales = []
    for name, value in (("duration_scale", duration_scale), ("amplitude_scale", amplitude_scale)):
        value = np.atleast_1d(np.asarray(value, dtype=np.float64))
        if value.ndim != 1 or len(value) not in (1, len(at)):
            raise ValueError(f"insert_swallows: {name} has {value.size} values for {len(at)} inserts; "
                             f"give one value or one per insert")
        scales.append(np.broadcast_to(value, at.shape))
    durations, amplitudes = scales
    if (durations <= 0).any():
        raise ValueError(f"insert_swallows: duration_scale must be positive, got {durations}")
    for onset, stretch, gain in zip(at, durations, amplitudes):
        start = onset + stretch * template.time[0]
        stop = onset + stretch * template.time[-1]
        if stop <= time[0] or start >= time[-1]:
            raise ValueError(f"insert_swallows: a swallow at {onset:g} s spans [{start:.2f}, {stop:.2f}] s, "
                             f"outside the track [{time[0]:.2f}, {time[-1]:.2f}] s")
        curve = gain * template((time - onset) / stretch)
        # The fades lie in the template's rest padding before the onset (and as long after) when it is long enough.
        lead = -stretch * template.time[0]
        fade = min(cfg.fade_seconds, lead if lead > 0 else 0.5 * (stop - start))
        ramp_in = np.clip((time - start) / fade, 0.0, 1.0)
        ramp_out = np.clip((stop - time) / fade, 0.0, 1.0)
        weight = 0.5 - 0.5 * np.cos(np.pi * np.minimum(ramp_in, ramp_out))
        if cfg.blend == "add":
            out = out + weight * curve
            continue
        before = (time >= start - cfg.rest_window_seconds) & (time <= start)
        after = (time >= stop) & (time <= stop + cfg.rest_window_seconds)
        level_before = np.median(out[..., before], axis=-1) if before.any() else None
        level_after = np.median(out[..., after], axis=-1) if after.any() else None
        if level_before is None and level_after is None:
            level_before = level_after = np.median(out, axis=-1)
        level_before = level_after if level_before is None else level_before
        level_after = level_before if level_after is None else level_after
        progress = np.clip((time - start) / (stop - start), 0.0, 1.0)
        rest = np.asarray(level_before)[..., None] * (1 - progress) + np.asarray(level_after)[..., None] * progress
        out = (1 - weight) * out + weight * (rest + curve)
    return out


# --------------------------------------------------------------------------- files


def write_template(path: str | Path, template: SwallowTemplate) -> None:
    """CSV ``time,tau,std`` (time 0 = onset), written atomically."""
    write_csv(path, {"time": template.time, "tau": template.tau, "std": template.std}, float_format="%.9g")


def read_template(path: str | Path) -> SwallowTemplate:
    """A template written by :func:`write_template`: CSV ``time,tau,std``, time 0 at the onset.

    Anything else (a tau track has ``time,tau`` too) is an InputError saying so: the ``std`` column is
    required, and time must start at or before the onset, 0 (the rest padding is negative time), and end after it.
    """
    path = Path(path)
    what = "a swallow template written by python -m motion.swallow (CSV time,tau,std; time 0 = onset)"
    if path.suffix.lower() != ".csv":
        raise InputError(f"{path}: not {what}: got '{path.suffix}'")
    table = CsvTable(path)
    if not table.has("std"):
        raise InputError(f"{path}: not {what}: no column 'std' (columns: {', '.join(table.header)})")
    if len(table) < 3:
        raise InputError(f"{path}: {len(table)} rows, a swallow template needs at least 3")
    time, tau, std = table.numeric("time"), table.numeric("tau"), table.numeric("std")
    check_increasing(time, table, "time")
    if not time[0] <= 0.0 < time[-1]:
        raise InputError(f"{path}: not {what}: column 'time' runs {time[0]:g} to {time[-1]:g} s, expected it to "
                         f"start at or before 0 (the onset) and end after it")
    if (std < 0).any():
        i = int(np.argmax(std < 0))
        raise InputError(f"{path}: column 'std', line {table.lines[i]}: negative ({std[i]:g}), expected >= 0")
    return SwallowTemplate(time, tau, std, estimate_fps(time), np.array([0.0]), ("onset",))


def read_tracks(paths: Sequence[str | Path], fps: float | None = None,
                min_confidence: float | None = None) -> list[TauTrack]:
    """Tau tracks from CSV or .npy files (``data.tau_track.read_tau_track``).

    ``fps``: the frame rate of files that carry none (.npy, a CSV with ``frame`` but no ``time``/``fps``);
    ``min_confidence``: tracker rows below it are dropped (files without a ``confidence`` column are read
    whole).  Errors name the config keys of ``configs/swallow.yaml``.
    """
    return [read_tau_track(p, fps=fps, min_confidence=min_confidence, fps_key="fps") for p in paths]


def plot_template(path: str | Path, build: TemplateBuild) -> None:
    """Aligned swallows, the template +- std and the naive unaligned mean, saved atomically."""
    t = build.template
    fig, ax = figure(figsize=(9, 5))
    for k, curve in enumerate(build.aligned):
        ax.plot(t.time, curve, color="0.6", lw=0.8, label="aligned swallows" if k == 0 else None)
    ax.fill_between(t.time, t.tau - t.std, t.tau + t.std, color="C0", alpha=0.25, label="template ± std")
    ax.plot(t.time, t.tau, color="C0", lw=2.2, label=f"template ({len(build.events)} swallows)")
    if len(build.naive_time) > 1:
        _, _, shift = shift_aligned_error(build.naive_time, build.naive_tau, t.time, t.tau,
                                          max_shift=max(2.0, build.naive_time[-1]), resolution=1.0 / t.fps)
        ax.plot(build.naive_time + shift, build.naive_tau, color="C3", ls="--", lw=1.6,
                label=f"naive unaligned mean (clip starts aligned, shifted {shift:+.2f} s)")
    bottom = ax.get_ylim()[0]
    for name, x in zip(t.landmark_names, t.landmarks):
        ax.axvline(x, color="0.3", ls=":", lw=0.8)
        ax.text(x, bottom, f" {name}", rotation=90, va="bottom", ha="right", fontsize=8)
    ax.set_xlim(t.time[0], t.time[-1])
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel("time from onset (s)")
    ax.set_ylabel("tau above rest (UV units; 0.03 ≈ 1 cm)")
    ax.set_title("Swallow template: landmark-registered mean")
    ax.legend(loc="upper right", fontsize=8)
    save_figure(fig, path, dpi=110)


def plot_playback(path: str | Path, track: TauTrack, out: np.ndarray, at: Sequence[float]) -> None:
    fig, ax = figure(figsize=(10, 4))
    ax.plot(track.time, track.tau, color="0.5", lw=1, label="input track")
    ax.plot(track.time, out, color="C0", lw=1.5, label="with swallows")
    for x in at:
        ax.axvline(x, color="C3", ls=":", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("tau (UV units)")
    ax.legend(loc="upper right", fontsize=8)
    save_figure(fig, path, dpi=110)


# --------------------------------------------------------------------------- CLI


def config_from(cfg: DictConfig) -> SwallowConfig:
    """SwallowConfig from the ``swallow`` section of a hydra config (unknown keys are an error)."""
    return config_dataclass(SwallowConfig, cfg.swallow, "swallow (configs/swallow.yaml)")


def run_template(cfg: DictConfig) -> TemplateBuild:
    """``mode=template``: read ``inputs``, build the template, write ``out`` (and ``plot``), print the report."""
    inputs = as_list(cfg.inputs)
    if not inputs:
        raise InputError("inputs=[a.csv,b.csv,...] is required (tau tracks: CSV or .npy)")
    if not cfg.out:
        raise InputError("out=template.csv is required")
    started = _time.perf_counter()
    config = config_from(cfg)
    tracks = read_tracks(inputs, cfg.fps, cfg.min_confidence)
    build = build_template(tracks, config)
    write_template(cfg.out, build.template)
    if cfg.plot:
        plot_template(cfg.plot, build)
    print(build.report())
    print(f"wrote {cfg.out}" + (f" and {cfg.plot}" if cfg.plot else "") + f" in {_time.perf_counter() - started:.1f} s")
    return build


def run_play(cfg: DictConfig) -> TauTrack:
    """``mode=play``: insert ``template`` into ``track`` at ``at`` seconds, write ``out`` (and ``plot``)."""
    for key, example in (("track", "in.csv"), ("template", "template.csv"), ("out", "out.csv")):
        if not cfg.get(key):
            raise InputError(f"mode=play needs {key}={example}")
    at = as_list(cfg.at)
    if not at:
        raise InputError("mode=play needs at=[t1,t2,...] (onset times in seconds)")
    try:
        at = [float(a) for a in at]
    except (TypeError, ValueError):
        raise InputError(f"at={at}: expected onset times in seconds (a number or a list of numbers)") from None
    config = config_from(cfg)
    (read,) = read_tracks([cfg.track], cfg.fps, cfg.min_confidence)
    track = uniform_track(read)  # over dropped tracker frames: the output is a complete frame,time,tau track
    template = read_template(cfg.template)
    durations, amplitudes = as_list(cfg.duration_scale), as_list(cfg.amplitude_scale)
    try:
        out = insert_swallows(track.tau, track.time, template, at, durations, amplitudes, config)
    except ValueError as e:
        raise InputError(f"{cfg.track}: {e}") from None
    result = TauTrack(out, track.time, track.fps, str(cfg.out))
    write_tau_track(cfg.out, result)
    if cfg.plot:
        plot_playback(cfg.plot, track, out, at)
    resampled = "" if track is read else (f" ({len(read)} rows resampled to {len(track)} uniform frames at "
                                          f"{track.fps:g} fps)")
    print(f"inserted {len(at)} swallow(s) (peak {template.peak_height:.4f} tau x amplitude {cfg.amplitude_scale}, "
          f"duration x {cfg.duration_scale}) into {cfg.track}{resampled} at {', '.join(f'{a:g}' for a in at)} s; "
          f"wrote {cfg.out}")
    return result


def run(cfg: DictConfig) -> TemplateBuild | TauTrack:
    """The CLI's work for a composed ``configs/swallow.yaml`` (tests call this in-process)."""
    if cfg.mode == "template":
        return run_template(cfg)
    if cfg.mode == "play":
        return run_play(cfg)
    raise InputError(f"mode={cfg.mode}: expected 'template' or 'play'")


if __name__ == "__main__":
    run_cli("swallow", run)
