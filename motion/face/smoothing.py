"""Causal smoothing of the face stage's tracks: the One Euro filter.

Casiez, Roussel and Vogel, "1 Euro Filter: A Simple Speed-based Low-pass Filter for Noisy Input in
Interactive Systems", CHI 2012: a first-order low-pass whose cutoff rises with the signal's speed,

    cutoff_t = min_cutoff + beta * |dx_t|,   alpha(c, dt) = 1 / (1 + 1 / (2 pi c dt)),
    x_t = x_{t-1} + alpha(cutoff_t, dt) (raw_t - x_{t-1}),

with dx the raw derivative low-passed at ``derivative_cutoff``: slow movement (a still face's jitter) is
smoothed hard, fast movement passes with little lag.  Causal (each output uses past frames only), so the
live mode can run the same filter.  Cutoffs in Hz, ``dt`` from the timestamps (variable-rate video).

Rotations are filtered as unit quaternions (``base.rotations``), each put on the side of the previous one,
then renormalised.  The parameters per track (:data:`WEIGHT_FILTER`, :data:`ROTATION_FILTER`) were set by
hand for about two frames of lag at 30 fps; whether ``face_smoothing`` is on by default was decided by
measuring jitter and lag with and without them (benchmarks/README.md, "Face video": off).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from base.rotations import matrix_to_quaternion, quaternion_to_matrix


@dataclass(frozen=True)
class OneEuro:
    """One Euro filter parameters: ``min_cutoff`` (Hz, the still-signal cutoff), ``beta`` (s per unit: how
    fast the cutoff rises with speed), ``derivative_cutoff`` (Hz)."""

    min_cutoff: float
    beta: float
    derivative_cutoff: float = 1.0

    def __call__(self, time: np.ndarray, values: np.ndarray) -> np.ndarray:
        """``values`` [T,...] at ``time`` [T] seconds (increasing) filtered causally, same shape and dtype."""
        raw = np.asarray(values, dtype=np.float64).reshape(len(values), -1)
        out = np.empty_like(raw)
        if len(raw) == 0:
            return np.asarray(values).copy()
        out[0] = raw[0]
        derivative = np.zeros(raw.shape[1])
        for t in range(1, len(raw)):
            dt = max(float(time[t] - time[t - 1]), 1e-6)
            speed = (raw[t] - out[t - 1]) / dt
            derivative += _alpha(self.derivative_cutoff, dt) * (speed - derivative)
            cutoff = self.min_cutoff + self.beta * np.abs(derivative)
            out[t] = out[t - 1] + _alpha(cutoff, dt) * (raw[t] - out[t - 1])
        return out.reshape(np.shape(values)).astype(np.asarray(values).dtype)


def _alpha(cutoff: float | np.ndarray, dt: float) -> float | np.ndarray:
    return 1.0 / (1.0 + 1.0 / (2.0 * np.pi * cutoff * dt))


def continuous_quaternions(rotations: np.ndarray) -> np.ndarray:
    """Quaternions [T,4] (w, x, y, z) of rotations [T,3,3], each on the side of the previous one."""
    quaternions = matrix_to_quaternion(torch.as_tensor(np.asarray(rotations, dtype=np.float64))).numpy()
    for t in range(1, len(quaternions)):
        if quaternions[t] @ quaternions[t - 1] < 0:
            quaternions[t] = -quaternions[t]
    return quaternions


def smooth_rotations(time: np.ndarray, rotations: np.ndarray, one_euro: OneEuro) -> np.ndarray:
    """Rotations [T,3,3] filtered as continuous unit quaternions, renormalised."""
    filtered = one_euro(time, continuous_quaternions(rotations))
    filtered /= np.linalg.norm(filtered, axis=1, keepdims=True)
    return quaternion_to_matrix(torch.as_tensor(filtered)).numpy().astype(np.asarray(rotations).dtype)


# beta in seconds per unit of speed: weights (in [0, 1]) per second; quaternion components (about half the
# angle in radians) per second.
WEIGHT_FILTER = OneEuro(min_cutoff=1.5, beta=0.3)
ROTATION_FILTER = OneEuro(min_cutoff=1.0, beta=3.0)
