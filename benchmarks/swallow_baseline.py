"""The five-landmark swallow baseline: a simple registration that templates from our own are measured against
(``bench_swallow_registration.py``, ``tests/test_swallow_register.py``).

Per clip: rest is the line through the medians of the first and last 0.3 s; the landmarks are the
maximum of the lightly smoothed curve and its 10% and 50% crossings either side; the curves are
warped piecewise-linearly to the mean landmark times and averaged.  This is the baseline issue 13
quotes for the recorded check; it shares none of detection's code, only the warping
(:func:`motion.swallow.register.register_curves`).

A clip is anything with ``time`` [T] (s), ``tau`` [T] and ``fps`` (``data.synthetic_tau``'s clips),
one swallow in it, with at least 0.3 s of rest at either end.
"""
from __future__ import annotations

import numpy as np
from scipy.ndimage import gaussian_filter1d

from motion.swallow.register import register_curves

REST_SECONDS = 0.3      # the rest line is fitted through the medians of this much track at either end
SMOOTH_SECONDS = 0.03   # Gaussian sigma of the curve the landmarks are read from
LEVELS = (0.1, 0.5)     # crossing levels, fractions of the maximum
GRID_FPS = 60.0         # the template's sampling
MARGIN_SECONDS = 0.4    # the template reaches this far beyond the first and last landmark


def level_crossing(time: np.ndarray, s: np.ndarray, p: int, level: float, step: int) -> float:
    """Time where ``s`` first falls to ``level`` x its value at sample ``p``, walking from ``p`` by ``step``
    (linear between samples)."""
    i = p
    while 0 < i < len(s) - 1 and s[i] > level * s[p]:
        i += step
    j = i - step
    return time[j] + (time[i] - time[j]) * (s[j] - level * s[p]) / (s[j] - s[i])


def five_landmarks(clips) -> tuple[list[np.ndarray], np.ndarray]:
    """Rest-removed curves (one [T] per clip) and [M, 5] landmark times: 10% and 50% crossings before the
    maximum, the maximum, 50% and 10% crossings after it."""
    marks, curves = [], []
    low, half = LEVELS
    for c in clips:
        n = int(round(REST_SECONDS * c.fps))
        t0, t1 = c.time[:n].mean(), c.time[-n:].mean()
        r0, r1 = np.median(c.tau[:n]), np.median(c.tau[-n:])
        x = c.tau - (r0 + (r1 - r0) * (c.time - t0) / (t1 - t0))
        s = gaussian_filter1d(x, SMOOTH_SECONDS * c.fps)
        p = int(np.argmax(s))
        marks.append([level_crossing(c.time, s, p, low, -1), level_crossing(c.time, s, p, half, -1), c.time[p],
                      level_crossing(c.time, s, p, half, 1), level_crossing(c.time, s, p, low, 1)])
        curves.append(x)
    return curves, np.array(marks)


def five_landmark_mean(clips) -> tuple[np.ndarray, np.ndarray]:
    """The baseline's template: (time [R] from the first landmark, tau [R]), the clips warped to their mean
    landmark times and averaged."""
    curves, marks = five_landmarks(clips)
    target = (marks - marks[:, :1]).mean(axis=0)
    grid = np.arange(-MARGIN_SECONDS, target[-1] + MARGIN_SECONDS, 1 / GRID_FPS)
    aligned = register_curves([c.time for c in clips], curves, marks, target, grid)
    return grid, np.nanmean(aligned, axis=0)
