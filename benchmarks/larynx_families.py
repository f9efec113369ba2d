"""The tau generators of the real-regime larynx benchmarks (``bench_larynx_real.py``, ``bench_larynx_bounds.py``):
four families of people whose larynx height tau (UV units, 30 fps) is a causal
function of real expression weights psi [T,55], each unlike the project's training generator
(``data.synthetic_larynx``) in lags and filters, nonlinearity, the cue that fires a swallow and the swallow's
shape, with per-person gains over a wide range; plus the families' own parts (articulation, swallows), which
the bounds read.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from data.expressions import EXPRESSION_NAMES
from data.synthetic_larynx import run_length
from data.synthetic_tau import SwallowShape, swallow_profile

FPS = 30.0  # the families' rate; the Live Link Face takes are 30 fps (bsw_list.npy stores none)
K = {name: k for k, name in enumerate(EXPRESSION_NAMES)}


# --------------------------------------------------------------------------- causal building blocks


def lagged(x: np.ndarray, frames: int) -> np.ndarray:
    """x delayed by ``frames`` (its first frame repeated in front), along axis 0."""
    if frames <= 0:
        return x
    return np.concatenate([np.repeat(x[:1], frames, axis=0), x])[: len(x)]


def low_pass(x: np.ndarray, time_constant: float, order: int = 1) -> np.ndarray:
    """``order`` cascaded first-order causal low-passes (order 2: critically damped), starting at x[0]."""
    a = math.exp(-1.0 / (FPS * time_constant))
    y = np.asarray(x, np.float64)
    for _ in range(order):
        out = np.empty_like(y)
        state = y[0]
        for t in range(len(y)):
            state = a * state + (1 - a) * y[t]
            out[t] = state
        y = out
    return y


def asymmetric(x: np.ndarray, rise: float, fall: float) -> np.ndarray:
    """Causal follower with one time constant going up and another coming down (a ratchet)."""
    up, down = math.exp(-1.0 / (FPS * rise)), math.exp(-1.0 / (FPS * fall))
    out = np.empty(len(x))
    state = x[0]
    for t, value in enumerate(x):
        a = up if value > state else down
        state = a * state + (1 - a) * value
        out[t] = state
    return out


def fire(cue: np.ndarray, refractory: float, since: float | None = None) -> list[int]:
    """Frames where the boolean ``cue`` switches on, at least ``refractory`` seconds apart (causal).

    ``since``: seconds from the last swallow before the first frame to that frame (None: long ago, the first
    onset fires)."""
    onsets = np.flatnonzero(cue[1:] & ~cue[:-1]) + 1
    last = -math.inf if since is None else -since * FPS
    kept: list[int] = []
    for frame in onsets:
        if frame - last >= refractory * FPS:
            kept.append(int(frame))
            last = frame
    return kept


def held_for(condition: np.ndarray, seconds: float) -> np.ndarray:
    """True where ``condition`` has held for the last ``seconds`` (causal)."""
    return run_length(condition) >= max(1, int(round(seconds * FPS)))


def swallows(num_frames: int, onsets: list[int], amplitudes: np.ndarray, duration: float,
             shape: SwallowShape) -> np.ndarray:
    seconds = np.arange(num_frames) / FPS
    out = np.zeros(num_frames)
    for frame, amplitude in zip(onsets, amplitudes):
        out += swallow_profile(seconds, frame / FPS, duration, float(amplitude), shape)
    return out


def mean_lr(psi: np.ndarray, name: str) -> np.ndarray:
    return 0.5 * (psi[:, K[name + "_L"]] + psi[:, K[name + "_R"]]).astype(np.float64)


# --------------------------------------------------------------------------- the families


@dataclass(frozen=True)
class Person:
    """A subject of a family: gains (log-uniform over a wide range), a lag and time constants."""

    gain: float      # overall articulation gain
    swallow: float   # swallow amplitude factor
    lag: float       # seconds
    tau_a: float     # seconds, the family's main time constant
    mix: np.ndarray  # per-term weights
    refractory: float | None = None  # seconds between swallows at least (None: the family's own)
    since: float | None = None       # seconds since the last swallow at the take's first frame (None: long ago)


# Spontaneous swallowing in healthy younger adults: 0.98 per minute on average, 95% CI 0.67-1.42 (Bulmer et al.
# 2021, "Evaluation of spontaneous swallow frequency in healthy people and those with, or at risk of developing,
# dysphagia: a review", Gerontology & Geriatric Medicine 7, doi:10.1177/23337214211041801).  The families' own
# refractory times (3-5 s) let their people swallow 1.4-10.5 times a minute on the recordings, at almost every cue.
PHYSIOLOGICAL_SPACING = (35.0, 85.0)  # seconds: with the wait for the next cue, about one swallow a minute
Spacing = tuple[float, float] | None   # person(): the swallows' spacing (seconds), None for the families' own


def person(family: str, subject: int, seed: int, terms: int, spacing: Spacing = None, take: int = 0) -> Person:
    """``subject`` of ``family`` at ``seed``.  ``spacing`` (low, high) seconds: the person's refractory time
    drawn log-uniform in it, and, per ``take``, the time since their last swallow before the take drawn uniform
    in [0, refractory] (None: the family's refractory, no swallow before the take)."""
    key = [seed, sum(map(ord, family)), subject]
    rng = np.random.default_rng([*key, 77])
    p = Person(gain=float(np.exp(rng.uniform(np.log(0.4), np.log(2.5)))),
               swallow=float(np.exp(rng.uniform(np.log(0.6), np.log(1.6)))),
               lag=float(rng.uniform(0.12, 0.35)), tau_a=float(rng.uniform(0.08, 0.25)),
               mix=rng.uniform(0.5, 1.5, terms))
    if spacing is None:
        return p
    low, high = spacing
    refractory = float(np.exp(np.random.default_rng([*key, 78]).uniform(np.log(low), np.log(high))))
    since = float(np.random.default_rng([*key, take, 79]).uniform(0, refractory))
    return dataclasses.replace(p, refractory=refractory, since=since)


def family_damped(psi: np.ndarray, p: Person) -> np.ndarray:
    """Linear articulation through a critically damped filter, lagged 120-350 ms; swallows at speech pauses.

    Swallow: the jaw stays closed (jawOpen < 0.1) for 0.5 s, at most one per 4 s; a single bump
    (no dip, no undershoot) of 0.9 s.
    """
    jaw, funnel, smile = psi[:, K["jawOpen"]], psi[:, K["mouthFunnel"]], mean_lr(psi, "mouthSmile")
    stretch, lower = mean_lr(psi, "mouthStretch"), mean_lr(psi, "mouthLowerDown")
    drive = (-0.040 * p.mix[0] * jaw - 0.030 * p.mix[1] * funnel + 0.025 * p.mix[2] * smile
             + 0.020 * p.mix[3] * stretch - 0.015 * p.mix[4] * lower)
    articulation = p.gain * low_pass(lagged(drive, int(round(p.lag * FPS))), p.tau_a, order=2)
    onsets = fire(held_for(jaw < 0.1, 0.5), p.refractory or 4.0, p.since)
    shape = SwallowShape(phases=[0.0, 0.45, 1.0], levels=[0.0, 1.0, 0.0])
    events = swallows(len(psi), onsets, np.full(len(onsets), 0.035 * p.swallow), 0.9, shape)
    return articulation + events


def family_saturating(psi: np.ndarray, p: Person) -> np.ndarray:
    """A saturating (tanh) mix of mouth and brow weights followed by a ratchet (fast rise, slow fall);
    swallows when the jaw snaps shut (from > 0.25 to < 0.1 within 0.3 s), biphasic with a deep undershoot."""
    jaw = psi[:, K["jawOpen"]].astype(np.float64)
    mix = (1.2 * p.mix[0] * jaw + 0.8 * p.mix[1] * mean_lr(psi, "mouthStretch")
           - 0.9 * p.mix[2] * psi[:, K["mouthPucker"]] + 0.6 * p.mix[3] * mean_lr(psi, "browInnerUp")
           - 0.5 * p.mix[4] * mean_lr(psi, "browDown"))
    level = 0.018 * p.gain * np.tanh(2.5 * (mix - 0.25))
    articulation = asymmetric(lagged(level, int(round(0.6 * p.lag * FPS))), 0.05, 0.2 + 2 * p.tau_a)
    window = int(0.3 * FPS)
    was_open = np.array([jaw[max(0, t - window):t + 1].max() for t in range(len(jaw))]) > 0.25
    onsets = fire(was_open & (jaw < 0.1), p.refractory or 3.0, p.since)
    amplitudes = 0.03 * p.swallow * (0.6 + np.array([jaw[max(0, f - window):f + 1].max() for f in onsets]))
    shape = SwallowShape(phases=[0.0, 0.3, 0.6, 1.0], levels=[0.0, 1.0, -0.5, 0.0])
    return articulation + swallows(len(psi), onsets, amplitudes, 1.3, shape)


def family_effort(psi: np.ndarray, p: Person) -> np.ndarray:
    """Slow effort (a leaky integral over 2-3 s of the mouth's speed, saturating) plus a jaw x smile
    interaction; swallows when a blink falls on a closed jaw (at most one per 5 s), with a plateau."""
    jaw, smile = psi[:, K["jawOpen"]].astype(np.float64), mean_lr(psi, "mouthSmile")
    mouth = [k for k, n in enumerate(EXPRESSION_NAMES) if n.startswith(("mouth", "jaw"))]
    speed = np.abs(np.diff(psi[:, mouth], axis=0, prepend=psi[:1, mouth])).sum(axis=1) * FPS
    effort = 0.012 * p.gain * np.tanh(low_pass(speed, 2.0 + 4 * p.tau_a) / 3.0)
    interaction = -0.03 * p.gain * p.mix[0] * low_pass(lagged(jaw * (0.3 + smile), int(round(p.lag * FPS))), 0.1)
    cue = (mean_lr(psi, "eyeBlink") > 0.5) & (jaw < 0.12)
    onsets = fire(cue, p.refractory or 5.0, p.since)
    shape = SwallowShape(phases=[0.0, 0.2, 0.65, 1.0], levels=[0.0, 1.0, 0.9, 0.0])
    return effort + interaction + swallows(len(psi), onsets, np.full(len(onsets), 0.03 * p.swallow), 1.0, shape)


def family_subject(psi: np.ndarray, p: Person) -> np.ndarray:
    """Per-subject everything: lag 120-350 ms, a subject-specific sign of the lip-rounding term, a squared
    jaw term, and swallows at pauses (jaw < 0.12 held 0.3 s, at most one per 3 s) whose duration scales
    with the subject's time constant, biphasic with the undershoot first."""
    jaw = psi[:, K["jawOpen"]].astype(np.float64)
    sign = 1.0 if p.mix[0] > 1.0 else -1.0
    drive = (-0.06 * p.mix[1] * jaw ** 2 + sign * 0.04 * p.mix[2] * psi[:, K["mouthPucker"]]
             + 0.03 * p.mix[3] * mean_lr(psi, "mouthSmile") - 0.03 * p.mix[4] * psi[:, K["mouthClose"]])
    articulation = p.gain * low_pass(lagged(drive, int(round(p.lag * FPS))), p.tau_a)
    onsets = fire(held_for(jaw < 0.12, 0.3), p.refractory or 3.0, p.since)
    shape = SwallowShape(phases=[0.0, 0.25, 0.6, 1.0], levels=[0.0, -0.4, 1.0, 0.0])
    events = swallows(len(psi), onsets, np.full(len(onsets), 0.04 * p.swallow), 0.7 + 2 * p.tau_a, shape)
    return articulation + events


FAMILIES = {"damped": family_damped, "saturating": family_saturating, "effort": family_effort,
            "subject": family_subject}
TRACKER_NOISE = 0.0007  # tau units, white



def family_tau(family: str, psi: np.ndarray, subject: int, seed: int, noise_seed: int, spacing: Spacing = None
               ) -> np.ndarray:
    """tau [T] of ``subject`` in ``family`` for psi [T,55] (30 fps), with white tracker noise; ``noise_seed``
    names the take (its noise and, with ``spacing``, the time since the person's last swallow)."""
    p = person(family, subject, seed, terms=5, spacing=spacing, take=noise_seed)
    tau = FAMILIES[family](psi.astype(np.float64), p)
    rng = np.random.default_rng([seed, subject, noise_seed, 5])
    return (tau + TRACKER_NOISE * rng.standard_normal(len(tau))).astype(np.float32)


def articulation_part(family: str, psi: np.ndarray, subject: int, seed: int) -> np.ndarray:
    """[T]: ``subject``'s tau without swallows (the family with the person's swallow amplitude set to 0) and
    without tracker noise."""
    p = person(family, subject, seed, terms=5)
    return FAMILIES[family](psi.astype(np.float64), dataclasses.replace(p, swallow=0.0))


def swallow_part(family: str, psi: np.ndarray, subject: int, seed: int, noise_seed: int = 0,
                 spacing: Spacing = None) -> np.ndarray:
    """[T]: ``subject``'s swallows' part of tau (no tracker noise) on the take ``noise_seed`` names."""
    p = person(family, subject, seed, terms=5, spacing=spacing, take=noise_seed)
    return FAMILIES[family](psi.astype(np.float64), p) - articulation_part(family, psi, subject, seed)


def swallow_frames(family: str, psi: np.ndarray, subject: int, seed: int, noise_seed: int = 0,
                   spacing: Spacing = None) -> np.ndarray:
    """bool [T]: the frames where ``subject``'s swallows move tau (:func:`swallow_part` exceeds 1e-4 UV)."""
    return np.abs(swallow_part(family, psi, subject, seed, noise_seed, spacing)) > 1e-4


def swallow_onsets(mask: np.ndarray) -> list[int]:
    """The first frames of the swallows in a :func:`swallow_frames` mask: where its runs start, a run less than
    2 s after the previous onset belonging to that swallow (a biphasic swallow crosses zero inside; every
    family's lasts at most 1.3 s and comes 3 s or more after the last)."""
    return fire(mask, 2.0)
