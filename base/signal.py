"""Small signal helpers shared by the motion modules (sub-sample extrema)."""
from __future__ import annotations

import math


def parabolic_peak(left: float, centre: float, right: float) -> tuple[float, float]:
    """Sub-sample extremum of three equally spaced samples: (offset, value) of the vertex of the
    parabola through (-1, left), (0, centre), (1, right).

    The offset (in samples, relative to the centre sample) is clipped to [-0.5, 0.5], the value is the
    parabola's at that offset; maxima and minima alike.  Flat (zero curvature) or non-finite samples
    give (0.0, centre).  With f(d) = centre + (right - left) / 2 d + (left - 2 centre + right) / 2 d^2,
    f'(d) = 0 at d = (left - right) / (2 (left - 2 centre + right)).
    """
    left, centre, right = float(left), float(centre), float(right)
    curvature = left - 2.0 * centre + right
    if curvature == 0.0 or not math.isfinite(curvature):
        return 0.0, centre
    offset = min(0.5, max(-0.5, 0.5 * (left - right) / curvature))
    return offset, centre + 0.5 * (right - left) * offset + 0.5 * curvature * offset * offset
