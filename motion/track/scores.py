"""Sub-pixel peaks of correlation score maps (the larynx match and the neck patches share them)."""
from __future__ import annotations

import numpy as np

from base.signal import parabolic_peak

# Least squares fit of f = a + b x + c y + d x^2 + e x y + g y^2 to the 3x3 values around a maximum.
_OFFSETS = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dtype=np.float64)
_QUADRATIC_FIT = np.linalg.pinv(np.stack([np.ones(9), _OFFSETS[:, 0], _OFFSETS[:, 1], _OFFSETS[:, 0] ** 2,
                                          _OFFSETS[:, 0] * _OFFSETS[:, 1], _OFFSETS[:, 1] ** 2], axis=1))


def subpixel_peak(scores: np.ndarray, col: int, row: int) -> tuple[float, float]:
    """Sub-pixel (x, y) of the maximum at (col, row) of a score map [h,w]: a 2-D quadratic through its 3x3
    neighbourhood (1-D parabolas along an axis where the fit is not a maximum or at the border)."""
    h, w = scores.shape
    if 0 < col < w - 1 and 0 < row < h - 1:
        a, b, c, d, e, g = _QUADRATIC_FIT @ scores[row - 1:row + 2, col - 1:col + 2].reshape(-1).astype(np.float64)
        det = 4 * d * g - e * e
        if d < 0 and det > 0:
            dx = (-2 * g * b + e * c) / det
            dy = (-2 * d * c + e * b) / det
            if abs(dx) <= 1 and abs(dy) <= 1:
                return col + dx, row + dy

    # (col, row) is the maximum, so each parabola's vertex is a maximum too (or the samples are flat: 0).
    dx = parabolic_peak(*scores[row, col - 1:col + 2])[0] if 0 < col < w - 1 else 0.0
    dy = parabolic_peak(*scores[row - 1:row + 2, col])[0] if 0 < row < h - 1 else 0.0
    return col + dx, row + dy
