"""Swallow detection: find swallows in a tau track by their main elevation and measure their landmarks.

A swallow is an excursion of the larynx slide ``tau`` above its rest level (``data.tau_track``):
it may rise in one or two stages (a first rise to about a third of the peak, a hold or slight dip,
the main elevation), stay up briefly and descend, with or without a dip below rest before and an
undershoot after (``data.synthetic_tau``).  Detection does not assume one of these shapes:

- Levels are measured from a rest baseline: a running low percentile of the strongly smoothed
  track, then twice a running median of the samples outside the swallows found, interpolated
  across them, so offsets, slow drift and quiet motion do not enter.
- Swallows are the main elevations: ``scipy.signal.find_peaks`` peaks of the strongly smoothed
  signal above the thresholds (height, prominence, width at half prominence), taken highest first;
  each claims its excursion (where the signal stays above ``split_fraction`` of its height), so a
  first stage, a plateau or a wobble on a swallow is part of it, not another swallow.
- Landmarks are measured on the lightly smoothed signal where this swallow has them, and only
  those; a missing one is noted (``SwallowEvent.missing``), never a reason to drop the swallow:

  - ``peak``: the highest point (sub-frame parabola);
  - ``rise<p>`` / ``fall<p>``: where the signal crosses ``p`` % of the height on the way up to /
    down from the peak (``crossing_levels``), kept where the level is crossed once: the first
    crossing coming from the peak and the first coming from rest lie within
    ``max_crossing_spread_seconds`` (a hold, shoulder or dip at that level, or noise on a flat
    stretch, puts them apart); ``rise50`` / ``fall50`` always (they define the width);
  - ``rise_max<k>`` / ``rise_min<k>`` / ``fall_max<k>`` / ``fall_min<k>``: intermediate peaks and
    valleys between rest and the peak (k-th from the peak outwards) standing out by
    ``feature_prominence`` of the height;
  - ``rise_start`` / ``fall_end``: where the rise leaves rest / the descent reaches it: the tangent
    at its steepest point below a quarter of the height meeting rest (``rest_point=tangent``), or
    the crossing of the rest band (``band``);
  - ``dip`` / ``undershoot``: a valley below the rest band before the rise / after the descent,
    and ``dip_start`` / ``undershoot_end`` where it leaves / reaches rest.

  The swallow's onset is ``dip_start`` if it has a dip, else ``rise_start``; its return
  ``undershoot_end`` or ``fall_end``.  The rest band is ``max(rest_fraction * height, noise_factor
  * spread at rest)``, the spread at rest (noise, quiet motion, baseline error) measured on the
  samples outside the swallows.
- Rejected (``TrackAnalysis.broken``), with the reason, is only a clearly broken swallow: one
  whose main elevation is cut by the track's start or end (no half-height crossing on a side).

Every duration is derived from the swallow itself (its rise and descent times), except the
configurable widths, whose defaults cover swallows of 0.5 to 4 s.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter1d, median_filter, percentile_filter
from scipy.signal import find_peaks

from base.signal import parabolic_peak
from base.timebase import resample_uniform
from data.tau_track import TauTrack

# Landmark names in time order (p: percent of the height; k: count from the peak outwards); a
# swallow has those it shows.
LANDMARK_NAMES: tuple[str, ...] = ("dip_start", "dip", "rise_start", "rise<p>", "rise_max<k>", "rise_min<k>", "peak",
                                   "fall_max<k>", "fall_min<k>", "fall<p>", "fall_end", "undershoot", "undershoot_end")
# The tangent of a tangent-intercept onset (return) is taken below this fraction of the height: within
# the first rise of a two-stage swallow (about a third of the peak, ``data.synthetic_tau``).
FIRST_RISE_LEVEL = 0.25
# The peak is the vertex of a parabola fitted within this fraction of the half-height width around the
# highest sample (the top ~5% of a parabola-like peak).
PEAK_FIT_FRACTION = 0.15


@dataclass
class DetectionConfig:
    """Thresholds of swallow detection (``configs/swallow.yaml: detection``).

    Seconds are track time, tau values in tau units (0.03 ~ 1 cm on HACK).  A human swallow
    raises the larynx by 1.5-2.5 cm (``data.synthetic_tau``), i.e. 0.045-0.075 tau, over 0.5-4 s
    from onset to return; speech wobble is 2-6 Hz, damped by ``detect_smooth_seconds``.
    """

    smooth_fraction: float = 0.04         # Gaussian sigma of the signal landmarks are read from, as a fraction
    #                                       of the swallow's width at half height (0.5 s wide: 0.02 s)
    detect_smooth_seconds: float = 0.08   # Gaussian sigma of the signal swallows are found in
    baseline_seconds: float = 10.0        # running window of the first baseline (> twice the longest swallow)
    rest_seconds: float = 2.0             # running median window over the rest samples (follows drift)
    min_prominence: float = 0.015         # tau units (~0.5 cm): scipy.signal.find_peaks prominence (after the
    #                                       detection smoothing, which takes ~20% off a 0.5 s swallow)
    min_height: float = 0.015             # tau units above the rest baseline
    min_width_seconds: float = 0.1        # main elevation's width at half prominence
    max_width_seconds: float = 3.0        # (a 4 s single-peak swallow is ~2 s wide at half height)
    split_fraction: float = 0.2           # two elevations are two swallows only if the signal between them
    #                                       falls below this fraction of the higher one
    rest_fraction: float = 0.05           # rest band = max(rest_fraction * height, noise_factor * spread at rest)
    noise_factor: float = 3.0             # (also: intermediate peaks/valleys stand out by noise_factor * noise)
    rest_point: str = "tangent"           # onset/return: tangent (tangent intercept) | band (band crossing)
    crossing_levels: list[float] = field(default_factory=lambda: [0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9])
    max_crossing_spread_seconds: float = 0.04  # a level crossed at times further apart than this is ambiguous
    feature_prominence: float = 0.08      # intermediate peaks/valleys: prominence >= this fraction of the height

    def __post_init__(self) -> None:
        if self.rest_point not in ("tangent", "band"):
            raise ValueError(f"DetectionConfig.rest_point must be 'tangent' or 'band', got '{self.rest_point}'")
        for key in ("baseline_seconds", "rest_seconds", "min_width_seconds"):
            if not getattr(self, key) > 0:
                raise ValueError(f"DetectionConfig.{key} must be positive, got {getattr(self, key)}")
        if not self.max_width_seconds > self.min_width_seconds:
            raise ValueError(f"DetectionConfig.max_width_seconds ({self.max_width_seconds}) must exceed "
                             f"min_width_seconds ({self.min_width_seconds})")
        if not 0 < self.split_fraction < 0.5:
            raise ValueError(f"DetectionConfig.split_fraction must be in (0, 0.5), got {self.split_fraction}")
        bad = [f for f in self.crossing_levels if not 0 < f < 1]
        if bad:
            raise ValueError(f"DetectionConfig.crossing_levels must lie in (0, 1), got {list(self.crossing_levels)}")


@dataclass
class SwallowEvent:
    """One swallow in a track.

    landmarks: name -> time (s, track time) of each landmark found, in time order; levels: name ->
    tau above the rest baseline there; height: the peak's; prominence: scipy's on the detection
    signal; missing: landmark name -> why this swallow has none (only onset, return, dip, undershoot
    and the half-height crossings are reported).  Names: see the module docstring.
    """

    landmarks: dict[str, float]
    levels: dict[str, float]
    height: float
    prominence: float
    missing: dict[str, str] = field(default_factory=dict)

    def has(self, name: str) -> bool:
        return name in self.landmarks

    def time(self, name: str) -> float:
        """The landmark's time (s), NaN if this swallow has none."""
        return float(self.landmarks.get(name, np.nan))

    @property
    def peak_time(self) -> float:
        return self.landmarks["peak"]

    @property
    def onset(self) -> float:
        """Where the swallow leaves rest (s): the start of its dip if it has one, else of its rise; NaN if neither."""
        return self.time("dip_start") if self.has("dip_start") else self.time("rise_start")

    @property
    def return_time(self) -> float:
        """Where the swallow is back at rest (s): the end of its undershoot if any, else of its descent; NaN
        if neither."""
        return self.time("undershoot_end") if self.has("undershoot_end") else self.time("fall_end")

    @property
    def duration(self) -> float:
        """Onset to return (s); NaN without either."""
        return self.return_time - self.onset

    @property
    def width(self) -> float:
        """Width of the main elevation at half height (s): ``fall50 - rise50``."""
        return self.time("fall50") - self.time("rise50")

    def notes(self) -> str:
        return "; ".join(f"{name}: {why}" for name, why in self.missing.items())


@dataclass
class TrackAnalysis:
    """Swallows of one uniformly sampled track and its rest baseline.

    events: swallows in time order; baseline [T] rest level (tau); noise: robust std of the white
    noise (tau); broken: why swallows were found but not measured; note: why no swallow was found.
    """

    events: list[SwallowEvent]
    baseline: np.ndarray
    noise: float
    broken: list[str] = field(default_factory=list)
    note: str = ""


def _smooth(x: np.ndarray, sigma_samples: float) -> np.ndarray:
    return gaussian_filter1d(x, sigma_samples, mode="nearest") if sigma_samples > 0.3 else x.copy()


def _smoothed_noise(noise: float, sigma_samples: float) -> float:
    """Std of white noise of std ``noise`` after :func:`_smooth` with ``sigma_samples``: noise * ||kernel||."""
    if sigma_samples <= 0.3:
        return noise
    impulse = np.zeros(int(8 * sigma_samples) * 2 + 1)
    impulse[len(impulse) // 2] = 1.0
    return float(noise * np.sqrt((gaussian_filter1d(impulse, sigma_samples, mode="constant") ** 2).sum()))


def white_noise_std(x: np.ndarray) -> float:
    """Robust std of the white noise in a smooth signal [T]: MAD of its second differences / sqrt(6)."""
    second = np.diff(x, 2)
    if len(second) == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(second - np.median(second))) / np.sqrt(6.0))


def _refine_extremum(x: np.ndarray, i: int) -> tuple[float, float]:
    """Sub-sample position and value of an extremum at sample ``i`` by a parabola through 3 samples."""
    if 0 < i < len(x) - 1:
        offset, value = parabolic_peak(x[i - 1], x[i], x[i + 1])
        return i + offset, value
    return float(i), float(x[i])


def _fit_peak(x: np.ndarray, i: int, half: int) -> tuple[float, float]:
    """Sub-sample position and value of the maximum near sample ``i``: the vertex of the least-squares
    parabola through the samples within ``half`` of ``i`` (kept within them), which averages the noise
    of 2 ``half`` + 1 samples; the 3-sample parabola where the window has fewer than 5 or the fit is not
    a maximum."""
    lo, hi = max(0, i - half), min(len(x) - 1, i + half)
    if hi - lo < 4:
        return _refine_extremum(x, i)
    offsets = np.arange(lo, hi + 1) - i
    c2, c1, c0 = np.polyfit(offsets, x[lo:hi + 1], 2)
    if c2 >= 0:
        return _refine_extremum(x, i)
    vertex = float(np.clip(-c1 / (2 * c2), lo - i, hi - i))
    return i + vertex, float(c0 + c1 * vertex + c2 * vertex * vertex)


def _crossing(sig: np.ndarray, start: int, stop: int, level: float) -> float | None:
    """From ``start`` towards ``stop`` (inclusive), the sub-sample position where ``sig`` first falls to
    ``level`` or below (linear between samples); None if it does not."""
    step = 1 if stop >= start else -1
    index = np.arange(start, stop + step, step)
    below = np.flatnonzero(sig[index] <= level)
    if len(below) == 0:
        return None
    k = int(below[0])
    if k == 0:
        return float(start)
    a, b = sig[index[k - 1]], sig[index[k]]
    fraction = (a - level) / (a - b) if a != b else 1.0
    return float(index[k - 1] + step * np.clip(fraction, 0.0, 1.0))


def _tangent_intercept(sig: np.ndarray, crossing: float, far: int, direction: int) -> float:
    """Where the tangent at the steepest point between the rest ``crossing`` and sample ``far`` (the
    end of the first rise, or of the descent into a valley) meets rest (0): the classic tangent-intercept
    onset, less biased than the band crossing for curves that leave rest with zero slope.  ``direction``
    -1 for onsets (rest lies at lower indices), +1 for returns.  Kept within |far - crossing| of the crossing,
    on the rest side."""
    lo, hi = sorted((int(round(crossing)), far))
    hi = min(hi, len(sig) - 1)
    if hi - lo < 2:
        return crossing
    slope = np.gradient(sig[lo:hi + 1])
    away = np.sign(sig[far]) * -direction  # the slope's sign going from rest into the excursion
    m = int(np.argmax(away * slope))
    if away * slope[m] <= 0:
        return crossing
    intercept = lo + m - sig[lo + m] / slope[m]
    reach = abs(far - crossing)
    if direction < 0:
        return float(np.clip(intercept, crossing - reach, crossing))
    return float(np.clip(intercept, crossing, crossing + reach))


def _side(sig: np.ndarray, peak: int, limit: int, direction: int, height: float, band: float, fine_noise: float,
          level_noise: float, fps: float, cfg: DetectionConfig, prefix: str, marks: dict, levels: dict,
          missing: dict) -> float | None:
    """Landmarks on one side of the peak (``direction`` -1: the rise, +1: the descent), up to sample ``limit``.

    ``fine_noise``: std of the white noise on ``sig``; ``level_noise``: of everything that moves a level
    (noise, quiet motion, baseline error: ``sig``'s spread at rest), which moves a crossing by
    ``level_noise / slope``.

    Fills ``marks`` / ``levels`` (sample positions, values) and ``missing`` (why a landmark is absent).
    Returns the sample position of the outermost point of the swallow on that side (its onset/return,
    else ``limit``).
    """
    rest_name, valley_name, valley_rest = (("rise_start", "dip", "dip_start") if direction < 0 else
                                           ("fall_end", "undershoot", "undershoot_end"))
    n = len(sig)

    def put(name: str, position: float) -> None:
        marks[name] = position
        levels[name] = float(np.interp(position, np.arange(n), sig))

    # Where the signal first re-enters the rest band coming from the peak.
    cross = _crossing(sig, peak, limit, band)
    inner_end = int(np.floor(cross)) if cross is not None else limit  # the excursion between peak and rest
    if direction > 0 and cross is not None:
        inner_end = int(np.ceil(cross))

    # Level crossings: unambiguous and steep enough.
    for f in cfg.crossing_levels:
        name = f"{prefix}{int(round(100 * f))}"
        position = _crossing(sig, peak, inner_end, f * height)
        if position is None:
            if abs(f - 0.5) < 1e-9:
                missing[name] = "the signal does not fall to half the height before the track end or the next swallow"
            continue
        # Coming from the peak the signal first falls below the level at ``position``; coming from rest
        # it first rises above it at ``inward``.  Where the two agree the level is crossed once, briskly;
        # where they do not, a hold, shoulder or dip at this level (or noise on a flat stretch) makes the
        # crossing ambiguous.  The half-height crossings are always kept (they define the width).
        inward = _crossing(-sig, inner_end, peak, -f * height)
        spread = abs(position - inward) if inward is not None else np.inf
        if abs(f - 0.5) < 1e-9:
            put(name, position)
        elif spread <= cfg.max_crossing_spread_seconds * fps:
            put(name, 0.5 * (position + inward))

    # Intermediate peaks and valleys between the peak and rest.
    lo, hi = sorted((peak, inner_end))
    if hi - lo >= 3:
        segment = sig[lo:hi + 1]
        threshold = max(cfg.feature_prominence * height, cfg.noise_factor * fine_noise)
        for kind, values in (("max", segment), ("min", -segment)):
            found, _ = find_peaks(values, prominence=threshold)
            found = [lo + int(i) for i in found if lo + int(i) != peak]
            found.sort(key=lambda i: abs(i - peak))
            for k, i in enumerate(found, start=1):
                position, _ = _refine_extremum(sig, i)
                put(f"{prefix}_{kind}{k}", position)

    label = "onset" if direction < 0 else "return"
    if cross is None:
        where = "the track start or the previous swallow" if direction < 0 else "the track end or the next swallow"
        missing[label] = f"the signal does not return to rest before {where}"
        return float(limit)

    def rest_point(crossing: float, anchor: int) -> float:
        if cfg.rest_point == "band":
            return crossing
        return _tangent_intercept(sig, crossing, anchor, direction)

    # Where the rise leaves rest (the descent reaches it): the tangent below FIRST_RISE_LEVEL of the height.
    reach = _crossing(-sig, int(round(cross)), peak, -FIRST_RISE_LEVEL * height)
    put(rest_name, rest_point(cross, int(round(reach)) if reach is not None else peak))
    outermost = marks[rest_name]

    # A valley below the rest band just beyond: within the side's own rise (descent) time.
    first = int(round(cross))
    span = abs(first - peak)
    far_valley = int(np.clip(first + direction * max(2, int(round(1.5 * span))), 0, n - 1))
    far_valley = max(far_valley, limit) if direction < 0 else min(far_valley, limit)
    a, b = sorted((first, far_valley))
    if b <= a:
        return outermost
    i = a + int(np.argmin(sig[a:b + 1]))
    if sig[i] >= -band:
        missing[valley_name] = (f"no valley below rest (lowest {sig[i] / height:+.2f} of the height, "
                                f"rest band {band / height:.2f})")
        return outermost
    if i == far_valley:
        missing[valley_name] = "the signal keeps falling below rest (no valley)"
        return outermost
    put(valley_name, _refine_extremum(sig, i)[0])
    outer = _crossing(np.abs(sig), i, limit, band)  # back into the rest band beyond the valley
    if outer is None:
        missing[valley_rest] = f"no rest after the {valley_name} before the track edge or the next swallow"
        return float(limit)
    put(valley_rest, rest_point(outer, i))
    return marks[valley_rest]


def _find_events(tau: np.ndarray, coarse: np.ndarray, baseline: np.ndarray, fps: float, noise: float,
                 cfg: DetectionConfig, start_time: float, rest: np.ndarray | None = None
                 ) -> tuple[list[SwallowEvent], list[tuple[int, int]], list[str]]:
    """Swallows in a track: ``tau`` [T] and ``coarse`` (strongly smoothed) [T], sample 0 at ``start_time``
    seconds; ``rest`` [T] the samples at rest (None: not known yet).
    Returns (events, their sample extents, reasons for broken swallows)."""
    n = len(tau)
    detect = coarse - baseline
    signals: dict[float, tuple[np.ndarray, float, float]] = {}

    def landmark_signal(sigma: float) -> tuple[np.ndarray, float, float]:
        """The signal landmarks are read from at Gaussian sigma (samples), its white-noise std and its
        spread at rest (noise, quiet motion, baseline error)."""
        sigma = round(sigma, 1)
        if sigma not in signals:
            sig = _smooth(tau, sigma) - baseline
            fine_noise = _smoothed_noise(noise, sigma)
            level_noise = fine_noise
            if rest is not None and rest.sum() >= 10:
                at_rest = sig[rest]
                level_noise = max(fine_noise, 1.4826 * float(np.median(np.abs(at_rest - np.median(at_rest)))))
            signals[sigma] = (sig, fine_noise, level_noise)
        return signals[sigma]

    # Rest (0) beyond both ends: a swallow cut by the track's start or end keeps its prominence and is
    # found (and then reported as broken if its main elevation is cut).
    peaks, props = find_peaks(np.concatenate([[0.0], detect, [0.0]]), height=cfg.min_height,
                              prominence=cfg.min_prominence,
                              width=(cfg.min_width_seconds * fps, cfg.max_width_seconds * fps))
    peaks = np.clip(peaks - 1, 0, n - 1)
    claimed = np.zeros(n, dtype=bool)
    accepted = []
    for j in np.argsort(-detect[peaks], kind="stable"):
        p = int(peaks[j])
        if claimed[p]:
            continue  # a first stage, a shoulder or a wobble of a higher swallow
        level = cfg.split_fraction * detect[p]
        a = p
        while a > 0 and detect[a - 1] > level and not claimed[a - 1]:
            a -= 1
        b = p
        while b < n - 1 and detect[b + 1] > level and not claimed[b + 1]:
            b += 1
        claimed[a:b + 1] = True
        accepted.append((p, a, b, float(props["prominences"][j]), float(props["widths"][j])))
    accepted.sort()
    events, extents, broken = [], [], []
    for k, (p, a, b, prominence, width) in enumerate(accepted):
        left = accepted[k - 1][2] + 1 if k > 0 else 0
        right = accepted[k + 1][1] - 1 if k + 1 < len(accepted) else n - 1
        # Scaled to the swallow: the landmark signal's smoothing and the peak's search window.
        sig, fine_noise, level_noise = landmark_signal(cfg.smooth_fraction * width)
        refine = max(1, int(round(0.25 * width)))
        lo, hi = max(a, p - refine), min(b, p + refine)
        i_peak = lo + int(np.argmax(sig[lo:hi + 1]))
        peak_pos, height = _fit_peak(sig, i_peak, max(1, int(round(PEAK_FIT_FRACTION * width))))
        if height <= 0:
            broken.append(f"swallow at {start_time + p / fps:.2f} s: its peak is not above the rest baseline")
            continue
        band = max(cfg.rest_fraction * height, cfg.noise_factor * level_noise)
        marks: dict[str, float] = {"peak": peak_pos}
        levels: dict[str, float] = {"peak": float(height)}
        missing: dict[str, str] = {}
        start = _side(sig, i_peak, left, -1, height, band, fine_noise, level_noise, fps, cfg, "rise", marks, levels,
                      missing)
        stop = _side(sig, i_peak, right, +1, height, band, fine_noise, level_noise, fps, cfg, "fall", marks, levels,
                     missing)
        cut = [side for side, name in (("start", "rise50"), ("end", "fall50")) if name not in marks]
        if cut:
            where = " and ".join("the track start or the previous swallow" if s == "start" else
                                 "the track end or the next swallow" for s in cut)
            broken.append(f"swallow at {start_time + peak_pos / fps:.2f} s is cut by {where} (no half-height crossing)")
            continue
        order = sorted(marks, key=marks.get)
        events.append(SwallowEvent({m: start_time + marks[m] / fps for m in order}, {m: levels[m] for m in order},
                                   float(height), prominence, missing))
        extents.append((int(np.floor(min(start, a))), int(np.ceil(max(stop, b)))))
    return events, extents, broken


def _rest_baseline(coarse: np.ndarray, rest: np.ndarray, fps: float, cfg: DetectionConfig) -> np.ndarray:
    """Running median of the rest samples, interpolated across the swallows."""
    index = np.arange(len(coarse))
    if rest.sum() < max(3, 0.05 * len(coarse)):
        return np.full(len(coarse), float(np.median(coarse[rest])) if rest.any() else float(np.median(coarse)))
    window = max(1, int(round(cfg.rest_seconds * fps)) | 1)
    level = median_filter(coarse[rest], size=window, mode="nearest")
    return np.interp(index, index[rest], level)


def analyse_track(tau: np.ndarray, fps: float, config: DetectionConfig | None = None,
                  start_time: float = 0.0) -> TrackAnalysis:
    """Detect swallows in a uniformly sampled tau track.

    Args:
        tau: [T] tau track (tau units), uniform at ``fps``, T >= 5, finite.
        fps: frames per second.
        config: thresholds (defaults: :class:`DetectionConfig`).
        start_time: time (s) of the first sample; landmark times are ``start_time + index / fps``.

    Returns:
        :class:`TrackAnalysis`: the swallows in time order, the rest baseline [T], the noise, the
        reasons for broken swallows and, when none was found, why.
    """
    cfg = config or DetectionConfig()
    tau = np.asarray(tau, dtype=np.float64)
    if tau.ndim != 1 or len(tau) < 5:
        raise ValueError(f"analyse_track: expected a tau track [T] with T >= 5, got shape {tau.shape}")
    if not np.isfinite(tau).all():
        raise ValueError(f"analyse_track: tau has {int((~np.isfinite(tau)).sum())} non-finite values")
    coarse = _smooth(tau, cfg.detect_smooth_seconds * fps)
    noise = white_noise_std(tau)
    window = max(1, int(round(cfg.baseline_seconds * fps)) | 1)
    # First pass: a low running percentile (a swallow may fill most of a short clip); then twice from rest.
    baseline = percentile_filter(coarse, 30, size=window, mode="nearest")
    events, extents, broken = _find_events(tau, coarse, baseline, fps, noise, cfg, start_time)
    for _ in range(2):
        if not extents:
            break
        rest = np.ones(len(tau), dtype=bool)
        margin = int(round(0.1 * fps))  # samples kept out of the rest baseline around each swallow
        for a, b in extents:
            rest[max(0, a - margin):b + margin + 1] = False
        baseline = _rest_baseline(coarse, rest, fps, cfg)
        events, extents, broken = _find_events(tau, coarse, baseline, fps, noise, cfg, start_time, rest)
    note = "" if events or broken else _why_no_swallow(coarse - baseline, fps, cfg)
    return TrackAnalysis(events, baseline, noise, broken, note)


def _why_no_swallow(detect: np.ndarray, fps: float, cfg: DetectionConfig) -> str:
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


def detect_swallows(tau: np.ndarray, fps: float, config: DetectionConfig | None = None,
                    start_time: float = 0.0) -> list[SwallowEvent]:
    """The swallows of :func:`analyse_track` (tau [T] uniform at ``fps``), in time order."""
    return analyse_track(tau, fps, config, start_time).events


def uniform_track(track: TauTrack) -> TauTrack:
    """The track itself if uniformly sampled at its fps, else linearly resampled at its fps."""
    steps = np.diff(track.time)
    if len(steps) == 0 or np.allclose(steps, 1.0 / track.fps, rtol=1e-3, atol=1e-6):
        return track
    time, tau = resample_uniform(track.time, track.tau, track.fps)
    return TauTrack(tau, time, track.fps, track.source)
