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
  those (:mod:`motion.swallow.landmarks`).
- Rejected (``TrackAnalysis.broken``), with the reason, is only a clearly broken swallow: one
  whose main elevation is cut by the track's start or end (no half-height crossing on a side).

Every duration is derived from the swallow itself (its rise and descent times), except the
configurable widths, whose defaults cover swallows of 0.5 to 4 s.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d, median_filter, percentile_filter
from scipy.signal import find_peaks

from base.timebase import resample_uniform
from data.tau_track import TauTrack
from motion.swallow.events import LANDMARK_NAMES, DetectionConfig, SwallowEvent, TrackAnalysis
from motion.swallow.landmarks import fit_peak, side_landmarks

__all__ = ["LANDMARK_NAMES", "DetectionConfig", "SwallowEvent", "TrackAnalysis", "analyse_track", "detect_swallows",
           "uniform_track", "white_noise_std"]

# The peak is the vertex of a parabola fitted within this fraction of the half-height width around the
# highest sample (the top ~5% of a parabola-like peak).
PEAK_FIT_FRACTION = 0.15


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
        peak_pos, height = fit_peak(sig, i_peak, max(1, int(round(PEAK_FIT_FRACTION * width))))
        if height <= 0:
            broken.append(f"swallow at {start_time + p / fps:.2f} s: its peak is not above the rest baseline")
            continue
        band = max(cfg.rest_fraction * height, cfg.noise_factor * level_noise)
        marks: dict[str, float] = {"peak": peak_pos}
        levels: dict[str, float] = {"peak": float(height)}
        missing: dict[str, str] = {}
        start = side_landmarks(sig, i_peak, left, -1, height, band, fine_noise, level_noise, fps, cfg, "rise",
                               marks, levels, missing)
        stop = side_landmarks(sig, i_peak, right, +1, height, band, fine_noise, level_noise, fps, cfg, "fall",
                              marks, levels, missing)
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
