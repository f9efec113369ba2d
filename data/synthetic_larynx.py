"""Synthetic expression sequences and the larynx slide they drive (for the expression -> larynx transformer).

Units and shapes:
- psi [T,55]: expression weights in [0, 1], ``data.expressions.EXPRESSION_NAMES`` order;
- tau [T]: larynx slide in UV units of the larynx map, + = up the neck (``data.synthetic_tau``;
  0.03 is about 1 cm), rest at about 0;
- fps: frames per second, explicit everywhere (default 30, the rate of iPhone face capture).

The expression generator draws a talking face: phrases of syllables built from a small viseme
table (jaw, lip spread, rounding, bilabial closure...), pauses, blinks, slow brow and gaze
movements, tracker noise, and swallows.  A swallow is marked in the expressions by what a
camera sees of it: the jaw closes, the lips close and press, the lower lip rolls in and the
chin rises (``mouthShrugLower``) for about half a second.

The larynx process :func:`larynx_response` is a *causal* function of psi (tau[t] depends on
psi[:t+1] only), nonlinear and subject dependent:
- articulation, lagged by 50-120 ms behind the face: the larynx lowers with jaw opening
  (quadratic) and lip rounding and rises with lip spreading, low-passed by an 80 ms inertia;
- effort: a saturating rise with the articulation speed integrated over ~1.5 s (phrases);
- swallows: when the lip press (with the jaw closed) crosses a threshold, a swallow profile
  (``data.synthetic_tau.swallow_profile``) starts, its amplitude set by the chin raise at that
  moment; a swallow in progress ignores further crossings.
These are modelling choices that give the learner a known, learnable target with the traits of
the real problem (lag, saturation, thresholds, memory, per-subject gains), not measured laws.
Training and held-out subjects are disjoint by id (held-out ids start at ``HELDOUT_SUBJECT_START``).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.signal import lfilter

from data.expressions import EXPRESSION_NAMES, NUM_EXPRESSIONS
from data.pairs import LarynxSequence
from data.synthetic_tau import SWALLOW_AMPLITUDE, SWALLOW_DURATION, swallow_profile

INDEX = {name: k for k, name in enumerate(EXPRESSION_NAMES)}
HELDOUT_SUBJECT_START = 10_000  # subject ids >= this are never used for training

# Viseme targets (HACK expression weights).  Consonants and vowels alternate in a syllable.
CONSONANTS: dict[str, dict[str, float]] = {
    "MBP": {"jawOpen": 0.04, "mouthClose": 0.15, "mouthPress_L": 0.2, "mouthPress_R": 0.2, "mouthRollLower": 0.1},
    "FV": {"jawOpen": 0.08, "mouthRollLower": 0.45, "mouthUpperUp_L": 0.2, "mouthUpperUp_R": 0.2},
    "TD": {"jawOpen": 0.22, "mouthStretch_L": 0.1, "mouthStretch_R": 0.1},
    "S": {"jawOpen": 0.07, "mouthStretch_L": 0.3, "mouthStretch_R": 0.3, "mouthSmile_L": 0.1, "mouthSmile_R": 0.1},
    "CH": {"jawOpen": 0.14, "mouthFunnel": 0.35, "mouthPucker": 0.2, "mouthShrugUpper": 0.2},
}
VOWELS: dict[str, dict[str, float]] = {
    "AA": {"jawOpen": 0.6, "mouthLowerDown_L": 0.3, "mouthLowerDown_R": 0.3},
    "EE": {"jawOpen": 0.15, "mouthStretch_L": 0.4, "mouthStretch_R": 0.4, "mouthSmile_L": 0.25,
           "mouthSmile_R": 0.25, "mouthUpperUp_L": 0.1, "mouthUpperUp_R": 0.1},
    "OO": {"jawOpen": 0.2, "mouthPucker": 0.65, "mouthFunnel": 0.4},
    "EH": {"jawOpen": 0.35, "mouthStretch_L": 0.15, "mouthStretch_R": 0.15, "mouthLowerDown_L": 0.15,
           "mouthLowerDown_R": 0.15},
}
MOUTH = [k for k, name in enumerate(EXPRESSION_NAMES) if name.startswith(("mouth", "jaw"))]

SWALLOW_PRESS_THRESHOLD = 0.35  # lip press (jaw closed) that starts a swallow; speech presses stay below


def _vector(weights: dict[str, float]) -> np.ndarray:
    out = np.zeros(NUM_EXPRESSIONS)
    for name, w in weights.items():
        out[INDEX[name]] = w
    return out


@dataclass(frozen=True)
class SubjectParams:
    """One synthetic subject: how they move their face and how their larynx follows.

    Expression style: ``neutral`` [55] offsets, ``articulation`` gain, ``syllable_rate`` (Hz).
    Larynx: ``rest`` (tau), ``lag`` (s), gains of the articulation terms (tau per unit weight),
    ``effort_gain`` (tau), ``swallow_amplitude`` (tau), ``swallow_duration`` (s), ``eta`` (larynx size).
    """

    subject: int
    neutral: np.ndarray
    articulation: float
    syllable_rate: float
    rest: float
    lag: float
    jaw_gain: float
    spread_gain: float
    round_gain: float
    effort_gain: float
    swallow_amplitude: float
    swallow_duration: float
    eta: float


def subject_params(subject: int, seed: int) -> SubjectParams:
    """The parameters of subject ``subject``, a deterministic function of (seed, subject)."""
    rng = np.random.default_rng([seed, subject, 1])
    neutral = np.zeros(NUM_EXPRESSIONS)
    for name in ("browInnerUp_L", "browInnerUp_R", "mouthSmile_L", "mouthSmile_R", "eyeSquint_L", "eyeSquint_R",
                 "mouthClose", "cheekSquint_L", "cheekSquint_R", "mouthRollUpper"):
        neutral[INDEX[name]] = rng.uniform(0.0, 0.06)
    eta = rng.uniform(0.8, 1.2)
    return SubjectParams(
        subject=subject, neutral=neutral, articulation=rng.uniform(0.75, 1.25), syllable_rate=rng.uniform(4.0, 5.5),
        rest=rng.normal(0.0, 0.0005), lag=rng.uniform(0.05, 0.12),
        jaw_gain=rng.uniform(0.025, 0.032), spread_gain=rng.uniform(0.015, 0.019), round_gain=rng.uniform(0.015, 0.019),
        effort_gain=rng.uniform(0.0065, 0.0075),
        swallow_amplitude=SWALLOW_AMPLITUDE * rng.uniform(0.92, 1.08),
        swallow_duration=SWALLOW_DURATION * rng.uniform(0.97, 1.03), eta=eta,
    )


# --------------------------------------------------------------------------- expressions


def _speech_keyframes(start: float, stop: float, params: SubjectParams, rng) -> list[tuple[float, np.ndarray]]:
    """Viseme keyframes (time s, target weights [55]) of one phrase."""
    keys = []
    t = start
    consonants, vowels = list(CONSONANTS.values()), list(VOWELS.values())
    while t < stop:
        period = rng.gamma(8.0, 1.0 / (8.0 * params.syllable_rate))
        gain = params.articulation * rng.uniform(0.6, 1.25)
        if rng.random() < 0.8:
            keys.append((t, gain * _vector(consonants[rng.integers(len(consonants))])))
        keys.append((t + 0.45 * period, gain * _vector(vowels[rng.integers(len(vowels))])))
        t += period
    return keys


def _pulse(time: np.ndarray, start: float, rise: float, hold: float, fall: float) -> np.ndarray:
    """Trapezoid envelope 0 -> 1 -> 0 with smooth (cosine) ramps."""
    up = np.clip((time - start) / rise, 0, 1)
    down = np.clip((time - start - rise - hold) / fall, 0, 1)
    return 0.5 * (1 - np.cos(np.pi * up)) * 0.5 * (1 + np.cos(np.pi * down))


def _band_noise(num_frames: int, fps: float, cutoff: float, rng) -> np.ndarray:
    """Unit-std noise low-passed below ``cutoff`` Hz."""
    x = gaussian_filter1d(rng.standard_normal(num_frames + 64), sigma=fps / (2 * np.pi * cutoff))[32:-32]
    return x / (x.std() + 1e-12)


def generate_expressions(num_frames: int, fps: float, params: SubjectParams, rng: np.random.Generator,
                         swallows_per_minute: float = 8.0, blinks_per_minute: float = 15.0,
                         expression_noise: float = 0.01) -> np.ndarray:
    """A talking face: psi [T,55] in [0, 1] at ``fps``.

    ``expression_noise`` is the standard deviation of white tracker noise on every weight.
    """
    time = np.arange(num_frames) / fps
    length = num_frames / fps
    # Phrases and pauses.
    keys: list[tuple[float, np.ndarray]] = [(0.0, np.zeros(NUM_EXPRESSIONS))]
    pauses: list[tuple[float, float]] = []
    t = rng.uniform(0.0, 1.5)
    pauses.append((0.0, t))
    while t < length:
        phrase = rng.uniform(1.5, 5.0)
        keys += _speech_keyframes(t, min(t + phrase, length), params, rng)
        t += phrase
        keys.append((t + 0.05, np.zeros(NUM_EXPRESSIONS)))
        pause = rng.uniform(0.6, 3.0)
        pauses.append((t, t + pause))
        t += pause
        keys.append((t - 0.05, np.zeros(NUM_EXPRESSIONS)))
    keys.sort(key=lambda k: k[0])
    key_times = np.array([k[0] for k in keys])
    key_values = np.stack([k[1] for k in keys])
    psi = np.stack([np.interp(time, key_times, key_values[:, j]) for j in range(NUM_EXPRESSIONS)], axis=1)
    psi = gaussian_filter1d(psi, sigma=0.03 * fps, axis=0)  # coarticulation

    # Swallows in pauses long enough to hold one.
    swallow_rate = swallows_per_minute / 60.0
    for start, stop in pauses:
        if stop - start < 1.0 or rng.random() > min(1.0, swallow_rate * (stop - start) * 2.5):
            continue
        onset = rng.uniform(start + 0.1, stop - 0.9)
        rise, hold = rng.uniform(0.1, 0.35), rng.uniform(0.3, 0.6)
        envelope = _pulse(time, onset, rise, hold, 0.15)
        press, chin = rng.uniform(0.5, 0.95), rng.uniform(0.15, 0.65)
        psi[:, INDEX["jawOpen"]] *= 1 - envelope
        for name, weight in (("mouthPress_L", press), ("mouthPress_R", press * rng.uniform(0.9, 1.1)),
                             ("mouthClose", 0.5 * press), ("mouthRollLower", 0.3), ("mouthShrugLower", chin)):
            psi[:, INDEX[name]] = np.maximum(psi[:, INDEX[name]], weight * envelope)

    # Blinks, slow brow and gaze movements, a smile now and then.
    for onset in rng.uniform(0, length, rng.poisson(blinks_per_minute * length / 60.0)):
        envelope = _pulse(time, onset, 0.07, 0.03, 0.12) * rng.uniform(0.8, 1.0)
        for name in ("eyeBlink_L", "eyeBlink_R"):
            psi[:, INDEX[name]] = np.maximum(psi[:, INDEX[name]], envelope * rng.uniform(0.95, 1.0))
    for name, amplitude in (("browInnerUp_L", 0.12), ("browDown_L", 0.08), ("eyeLookUp_L", 0.1),
                            ("eyeLookOut_L", 0.15), ("mouthSmile_L", 0.1), ("cheekSquint_L", 0.06)):
        slow = amplitude * np.clip(_band_noise(num_frames, fps, 0.3, rng), 0, None)
        psi[:, INDEX[name]] += slow
        psi[:, INDEX[name[:-1] + "R"]] += slow * rng.uniform(0.8, 1.0)
    psi += params.neutral
    psi += expression_noise * rng.standard_normal(psi.shape)
    return np.clip(psi, 0.0, 1.0).astype(np.float32)


# --------------------------------------------------------------------------- larynx


def _low_pass(x: np.ndarray, fps: float, time_constant: float) -> np.ndarray:
    """Causal first-order low-pass (exponential smoothing) along axis 0, starting at rest (0)."""
    a = np.exp(-1.0 / (fps * time_constant))
    return lfilter([1 - a], [1, -a], x, axis=0)


def larynx_response(psi: np.ndarray, fps: float, params: SubjectParams) -> np.ndarray:
    """tau [T] driven by psi [T,55] at ``fps``: causal (tau[t] uses psi[:t+1]), nonlinear, subject dependent."""
    psi = np.asarray(psi, dtype=np.float64)
    num_frames = len(psi)
    lag = int(round(params.lag * fps))
    lagged = np.concatenate([np.repeat(psi[:1], lag, axis=0), psi])[:num_frames]
    w = {name: lagged[:, INDEX[name]] for name in EXPRESSION_NAMES}
    now = {name: psi[:, INDEX[name]] for name in EXPRESSION_NAMES}

    jaw = w["jawOpen"]
    spread = 0.5 * (w["mouthStretch_L"] + w["mouthStretch_R"]) * (1 - jaw)
    rounding = w["mouthPucker"] * (0.5 + w["mouthFunnel"])
    posture = params.spread_gain * spread - params.round_gain * rounding - params.jaw_gain * jaw**2
    articulation = _low_pass(posture, fps, 0.08)

    speed = np.abs(np.diff(lagged[:, MOUTH], axis=0, prepend=lagged[:1, MOUTH])).sum(axis=1) * fps
    effort = params.effort_gain * np.tanh(_low_pass(speed, fps, 1.5) / 4.0)

    # The swallow reflex follows the lip seal without the subject's articulation lag.
    press = np.minimum(now["mouthPress_L"], now["mouthPress_R"]) * (1 - now["jawOpen"])
    time = np.arange(num_frames) / fps
    swallows = np.zeros(num_frames)
    crossings = np.flatnonzero((press[1:] >= SWALLOW_PRESS_THRESHOLD) & (press[:-1] < SWALLOW_PRESS_THRESHOLD)) + 1
    busy_until = -np.inf
    for frame in crossings:
        if time[frame] < busy_until:
            continue
        amplitude = params.swallow_amplitude * (0.55 + 1.2 * now["mouthShrugLower"][frame])
        swallows += swallow_profile(time, time[frame], params.swallow_duration, amplitude)
        busy_until = time[frame] + params.swallow_duration
    return params.rest + articulation + effort + swallows


# --------------------------------------------------------------------------- datasets


def subject_name(subject: int) -> str:
    """The name of synthetic subject ``subject`` in datasets and checkpoints."""
    return f"s{subject}"


def split_subjects(num_train: int, num_heldout: int) -> tuple[list[int], list[int]]:
    """Disjoint subject ids: training 0..num_train-1, held-out from ``HELDOUT_SUBJECT_START``."""
    if num_train > HELDOUT_SUBJECT_START:
        raise ValueError(f"at most {HELDOUT_SUBJECT_START} training subjects, got {num_train}")
    return list(range(num_train)), list(range(HELDOUT_SUBJECT_START, HELDOUT_SUBJECT_START + num_heldout))


def make_sequence(subject: int, index: int, num_frames: int, fps: float, seed: int,
                  tau_noise: float = 0.0005, **expression_options) -> LarynxSequence:
    """Sequence ``index`` of ``subject``: deterministic from (seed, subject, index).

    ``tau_noise`` (tau units) is the standard deviation of white measurement noise on tau, as a tracker adds;
    ``expression_options`` go to :func:`generate_expressions` (swallows_per_minute, blinks_per_minute,
    expression_noise).
    """
    params = subject_params(subject, seed)
    rng = np.random.default_rng([seed, subject, 2, index])
    psi = generate_expressions(num_frames, fps, params, rng, **expression_options)
    tau = larynx_response(psi, fps, params) + tau_noise * rng.standard_normal(num_frames)
    name = subject_name(subject)
    return LarynxSequence(psi, tau.astype(np.float32), float(fps), name, f"{name}_{index}", float(params.eta))


def make_dataset(subjects: Sequence[int], sequences_per_subject: int, seconds: float, fps: float, seed: int,
                 **options) -> list[LarynxSequence]:
    """``sequences_per_subject`` sequences of ``seconds`` for each subject (``options``: see :func:`make_sequence`)."""
    num_frames = int(round(seconds * fps))
    return [make_sequence(s, i, num_frames, fps, seed, **options)
            for s in subjects for i in range(sequences_per_subject)]
