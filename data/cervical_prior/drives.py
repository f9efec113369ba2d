"""Smooth drives of the prior (step 2 of ``data.cervical_prior.generator``): minimum-jerk moves between held
targets [FH85] and enveloped oscillations; sagittal, axial and lateral, in [-1, 1].

[FH85] Flash & Hogan, J Neurosci 5:1688-1703, 1985: minimum-jerk movements.
"""
from __future__ import annotations

import numpy as np

from data.cervical_prior.invivo import AXIAL_DRIVE, LATERAL_DRIVE, MOTION_KINDS, SAGITTAL_DRIVE, SATURATION_POWER


def saturate(x: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Smooth saturation of x towards ``upper`` (> 0) above zero and ``lower`` (< 0) below."""
    bound = np.where(x >= 0, upper, -lower)
    return x / (1.0 + np.abs(x / bound) ** SATURATION_POWER) ** (1.0 / SATURATION_POWER)


def minimum_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk position profile on tau in [0, 1] [FH85]: 10t^3 - 15t^4 + 6t^5."""
    t = np.clip(tau, 0.0, 1.0)
    return t**3 * (10 - 15 * t + 6 * t**2)


def held_transitions(rng: np.random.Generator, time: np.ndarray, amplitude: float) -> np.ndarray:
    """Minimum-jerk moves between targets uniform in [-amplitude, amplitude], each held 0-1 s. -> [T].

    A move over a drive distance D lasts U(0.6, 1.0) + 0.6 D seconds (longer moves take longer, as in
    Fitts' law; assumption), so a full swing from -1 to 1 peaks at about 1.9 drive units per second.
    """
    value = np.full(len(time), rng.uniform(-amplitude, amplitude))
    start = time[0] + rng.uniform(0.0, 0.8)
    current = value[0]
    while start < time[-1]:
        target = rng.uniform(-amplitude, amplitude)
        duration = rng.uniform(0.6, 1.0) + 0.6 * abs(target - current)
        value = value + (target - current) * minimum_jerk((time - start) / duration)
        current = target
        start += duration + rng.uniform(0.0, 1.0)
    return value


def enveloped_oscillation(rng: np.random.Generator, time: np.ndarray, amplitude: float,
                          frequency: tuple[float, float]) -> np.ndarray:
    """A sinusoid at a random frequency, faded in and out with minimum-jerk ramps (0.3 s) over a random window."""
    f = rng.uniform(*frequency)
    span = time[-1] - time[0]
    on = time[0] + rng.uniform(0.0, 0.4) * span
    off = on + rng.uniform(0.4, 1.0) * (time[-1] - on)
    ramp = 0.3
    envelope = minimum_jerk((time - on) / ramp) * (1.0 - minimum_jerk((time - off + ramp) / ramp))
    return amplitude * envelope * np.sin(2 * np.pi * f * (time - on))


def motion_drives(rng: np.random.Generator, num_frames: int, fps: float, kind: str) -> np.ndarray:
    """Drives [T,3] (sagittal, axial, lateral) in [-1, 1] of one motion ``kind`` at ``fps``."""
    if kind not in MOTION_KINDS:
        raise ValueError(f"unknown motion kind '{kind}', expected one of {', '.join(MOTION_KINDS)}")
    time = np.arange(num_frames) / fps
    drives = np.stack([held_transitions(rng, time, 0.12) for _ in range(3)], axis=1)  # small background drift
    main = {"nod": SAGITTAL_DRIVE, "turn": AXIAL_DRIVE, "tilt": LATERAL_DRIVE}
    if kind == "nod":
        drives[:, SAGITTAL_DRIVE] = held_transitions(rng, time, 0.35) + enveloped_oscillation(
            rng, time, rng.uniform(0.05, 0.3), (0.8, 2.0))
    elif kind in main:
        drives[:, main[kind]] = held_transitions(rng, time, 1.0)
        if kind == "turn" and rng.random() < 0.3:  # head shake "no"
            drives[:, AXIAL_DRIVE] += enveloped_oscillation(rng, time, rng.uniform(0.1, 0.25), (1.0, 2.5))
    else:
        drives = np.stack([held_transitions(rng, time, 0.8) for _ in range(3)], axis=1)
        if rng.random() < 0.3:
            axis = rng.integers(3)
            drives[:, axis] += enveloped_oscillation(rng, time, rng.uniform(0.05, 0.25), (0.8, 2.0))
    return saturate(drives, np.float64(-1.0), np.float64(1.0))
