"""The voice term's slope and time constants fitted from pair files that carry F0 (``data.pairs``, ``f0``).

Model, per pair: ``r(t) = c + k * g(t; rise, fall)`` where ``r`` is the pair's tau minus what the
expression model predicts from its psi (``checkpoint=``; ``none``: tau itself), ``g`` the larynx height of
``motion.voice.term`` at a slope of 1 mm per semitone (``knee``, ``high_ratio`` and ``hold`` fixed at the
given values), ``c`` a per-pair constant (the voice term is zero-mean over a take) and ``k = slope *
TAU_PER_MM``.  For given time constants ``k`` is linear least squares over all pairs; ``rise`` and ``fall``
minimise the remaining squared error (a log-spaced grid, then Nelder-Mead in log seconds).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize

from base.errors import InputError
from data.pairs import LarynxSequence
from motion.voice.config import TAU_PER_MM, VoiceConfig
from motion.voice.term import voice_height

GRID = np.geomspace(0.02, 0.5, 8)  # s: the time constants' search grid (larynx movements of 20-500 ms)


@dataclass
class VoiceFit:
    """A fit's result: the fitted parameters and how well they explain the pairs."""

    voice: VoiceConfig
    r2: float            # of the per-pair centred residual tau explained by the voice term
    pairs: int
    frames: int
    voiced: float        # fraction of voiced frames

    def report(self) -> dict:
        return {"r2": round(self.r2, 4), "pairs": self.pairs, "frames": self.frames, "voiced": round(self.voiced, 4),
                "slope_mm_per_octave": round(12 * self.voice.slope, 3)}


def _unit_heights(pairs: list[tuple[np.ndarray, float]], base: VoiceConfig, rise: float,
                  fall: float) -> list[np.ndarray]:
    unit = dataclasses.replace(base, slope=1.0, rise=rise, fall=fall)
    out = []
    for f0, fps in pairs:
        height = voice_height(f0, 1.0 / fps, unit)
        out.append(np.zeros(len(f0)) if height is None else height)
    return out


def _solve(heights: list[np.ndarray], residuals: list[np.ndarray]) -> tuple[float, float, float]:
    """(k, remaining squared error, total squared error) over per-pair centred series."""
    cross = power = total = 0.0
    for g, r in zip(heights, residuals):
        gc, rc = g - g.mean(), r - r.mean()
        cross += float(gc @ rc)
        power += float(gc @ gc)
        total += float(rc @ rc)
    if power <= 0:
        return 0.0, total, total
    return cross / power, total - cross * cross / power, total


def fit_voice(pairs: list[LarynxSequence], residuals: list[np.ndarray], base: VoiceConfig | None = None) -> VoiceFit:
    """Fit ``slope``, ``rise`` and ``fall`` (the rest of ``base`` fixed) to ``residuals`` [T] per pair (tau minus
    the expression model's prediction), given each pair's ``f0``."""
    base = base or VoiceConfig()
    if not pairs:
        raise InputError("no pairs to fit the voice term to")
    for pair in pairs:
        if pair.f0 is None:
            raise InputError(f"{pair.name}: a pair without 'f0'; expected pairs made with python -m data.pairs "
                             f"... audio=<the take's sound>")
    series = [(np.asarray(p.f0, np.float64), float(p.fps)) for p in pairs]
    voiced = float(np.mean(np.concatenate([f0 > 0 for f0, _ in series])))
    if voiced == 0:
        raise InputError(f"{pairs[0].name} ...: no voiced frame in {len(pairs)} pair(s); expected speech or song")
    residuals = [np.asarray(r, np.float64) for r in residuals]

    def error(log_tc: np.ndarray) -> float:
        rise, fall = np.exp(np.clip(log_tc, -6.0, 2.0))
        return _solve(_unit_heights(series, base, rise, fall), residuals)[1]

    start = min(((rise, fall) for rise in GRID for fall in GRID), key=lambda tc: error(np.log(tc)))
    best = minimize(error, np.log(start), method="Nelder-Mead",
                    options={"xatol": 1e-3, "fatol": 1e-12, "maxiter": 300})
    rise, fall = (float(v) for v in np.exp(np.clip(best.x, -6.0, 2.0)))
    k, remaining, total = _solve(_unit_heights(series, base, rise, fall), residuals)
    voice = dataclasses.replace(base, slope=k / TAU_PER_MM, rise=rise, fall=fall)
    return VoiceFit(voice, 1.0 - remaining / total if total > 0 else 0.0, len(pairs),
                    sum(len(f0) for f0, _ in series), voiced)
