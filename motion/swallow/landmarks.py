"""Landmarks of one swallow: what it shows on either side of its peak, measured on the lightly smoothed signal.

Only the landmarks this swallow has are measured; a missing one is noted (``SwallowEvent.missing``),
never a reason to drop the swallow:

- ``peak``: the highest point (sub-frame parabola, :func:`fit_peak`);
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
"""
from __future__ import annotations

import numpy as np
from scipy.signal import find_peaks

from base.signal import parabolic_peak
from motion.swallow.events import DetectionConfig

# The tangent of a tangent-intercept onset (return) is taken below this fraction of the height: within
# the first rise of a two-stage swallow (about a third of the peak, ``data.synthetic_tau``).
FIRST_RISE_LEVEL = 0.25


def _refine_extremum(x: np.ndarray, i: int) -> tuple[float, float]:
    """Sub-sample position and value of an extremum at sample ``i`` by a parabola through 3 samples."""
    if 0 < i < len(x) - 1:
        offset, value = parabolic_peak(x[i - 1], x[i], x[i + 1])
        return i + offset, value
    return float(i), float(x[i])


def fit_peak(x: np.ndarray, i: int, half: int) -> tuple[float, float]:
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


def side_landmarks(sig: np.ndarray, peak: int, limit: int, direction: int, height: float, band: float,
                   fine_noise: float, level_noise: float, fps: float, cfg: DetectionConfig, prefix: str, marks: dict,
                   levels: dict, missing: dict) -> float | None:
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
