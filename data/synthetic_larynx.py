"""Synthetic expression sequences and the larynx slide they drive (for the expression -> larynx transformer).

Units and shapes:
- psi [T,55]: expression weights in [0, 1], ``data.expressions.EXPRESSION_NAMES`` order;
- tau [T]: larynx slide in UV units of the larynx map, + = up the neck (``data.synthetic_tau``;
  0.03 is about 1 cm), rest near 0;
- fps: frames per second, explicit everywhere (default 30, the rate of iPhone face capture).

The expression generator draws a talking face: phrases of syllables built from a small viseme
table (jaw, lip spread, rounding, bilabial closure...), pauses, blinks, slow brow and gaze
movements, tracker noise, and swallows.  A swallow is marked in the expressions by what a
camera sees of it, in the subject's own way (their *swallow signature*: how much of the seal is a
lip press, a lower-lip roll or a lip closure), with the jaw closed and the chin raised
(``mouthShrugLower``), for about half a second.

The larynx process :func:`larynx_response` is a *causal* function of psi (tau[t] depends on
psi[:t+1] only), nonlinear and subject dependent:
- articulation, lagged behind the face: the larynx lowers with jaw opening (a power of it) and lip
  rounding and rises with lip spreading, softly saturating, low-passed by a first- or second-order
  inertia;
- effort: a saturating rise with the articulation speed integrated over a second or more (phrases);
- swallows: when the person's cue switches on (:func:`swallow_cue`; by default the seal, the
  signature's mix of press, roll and closure with the jaw closed, crossing a threshold), a swallow
  profile (``data.synthetic_tau.swallow_profile``, with the subject's own landmark levels and duration)
  starts, its amplitude set by the chin raise at that moment; for the subject's refractory time after a
  swallow's onset (at least its duration) further crossings are ignored.
  The face seals more often than the larynx swallows (a second seal follows some swallows within a few
  seconds), so whether a seal is a swallow depends on how long ago the last one was: a timing rule that
  needs seconds of memory, as swallows cued by the face in real captures do.
Every factor is drawn per subject from the ranges of a :class:`GeneratorRanges`: the training
subjects from :data:`TRAINING_RANGES`, held-out subjects from :func:`heldout_ranges` (longer lags,
slower filters, gains and powers reaching outside the training ranges, other swallow shapes), so a
validation on them measures generalisation to people unlike the training ones.
These are modelling choices that give the learner a known, learnable target with the traits of
the real problem (lag, saturation, thresholds, memory, per-subject gains), not measured laws.
Training and held-out subjects are disjoint by id (held-out ids start at ``HELDOUT_SUBJECT_START``).
"""
from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d, maximum_filter1d
from scipy.signal import lfilter

from data.expressions import EXPRESSION_NAMES, NUM_EXPRESSIONS
from data.pairs import LarynxSequence
from data.synthetic_tau import (
    SWALLOW_AMPLITUDE,
    SWALLOW_DURATION,
    SWALLOW_LANDMARK_LEVELS,
    SwallowShape,
    swallow_profile,
)

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

# Seal (the signature's mix of press, roll and closure, jaw closed) that starts a swallow.  Speech stays
# below it except where a viseme happens to seal hard in a subject's signature (FV's lower-lip roll):
# the cue is not unambiguous.
SWALLOW_SEAL_THRESHOLD = 0.35

# What a person's swallows follow (their *cue*, drawn per person from GeneratorRanges.cues):
# - "seal": the signature's seal crossing SWALLOW_SEAL_THRESHOLD (above);
# - "pause": the jaw kept below the person's cue_level for cue_hold seconds (a pause in speech);
# - "snap": the jaw falling below cue_level after being open past cue_open within the last cue_hold seconds;
# - "blink": a blink (eyeBlink, mean of both sides, above 0.5) while the jaw is below cue_level.
# Modelling choices: the face shows what precedes a swallow in several ways, and which way a person's
# larynx follows is a property of the person that a few minutes of their pairs have to reveal.  The
# default generator's people all swallow at a seal (data.swallow_cues); with several kinds, the trained
# model cannot yet tell whose swallows follow what (benchmarks/README.md, "Swallow cues").
SWALLOW_CUES = ("seal", "pause", "snap", "blink")


def _vector(weights: dict[str, float]) -> np.ndarray:
    out = np.zeros(NUM_EXPRESSIONS)
    for name, w in weights.items():
        out[INDEX[name]] = w
    return out


Range = tuple[float, float]


@dataclass(frozen=True)
class GeneratorRanges:
    """The ranges each subject factor is drawn from (uniformly; ``gain`` log-uniformly).

    ``lag`` (s) of articulation behind the face; ``inertia`` (s) the articulation low-pass time constant,
    ``second_order`` the share of subjects whose low-pass is second order (critically damped);
    ``gain`` the factor on all articulation gains; ``jaw_power`` the exponent of the jaw term;
    ``saturation`` (tau) the knee of the soft clip of the articulation posture; ``effort_time`` (s) the
    integration time of effort and ``effort_gain`` its size (tau); ``signature`` the range of each of the
    three seal weights (press, roll, closure) before normalisation; ``swallow_duration`` and
    ``swallow_amplitude`` factors of SWALLOW_DURATION / SWALLOW_AMPLITUDE; ``dip`` and ``undershoot``
    the swallow's valley levels (fractions of its amplitude; the defaults' are -0.12 and -0.22);
    ``swallow_refractory`` (s) the shortest time from one swallow's onset to the next (a modelling choice:
    a seal within it is no swallow); ``cues`` the kinds of swallow cue a person is drawn from (uniformly,
    :data:`SWALLOW_CUES`), ``cue_level`` the jawOpen below which the jaw counts as closed, ``cue_hold`` (s)
    how long a pause lasts before it cues, or how recently the jaw was open for a snap, ``cue_open`` the
    jawOpen a snap comes down from.
    """

    lag: Range = (0.03, 0.15)
    inertia: Range = (0.04, 0.12)
    second_order: float = 0.5
    gain: Range = (0.7, 1.5)
    jaw_power: Range = (1.6, 2.4)
    saturation: Range = (0.015, 0.03)
    effort_time: Range = (1.0, 2.0)
    effort_gain: Range = (0.004, 0.009)
    signature: Range = (0.0, 1.0)
    swallow_duration: Range = (0.85, 1.15)
    swallow_amplitude: Range = (0.75, 1.25)
    dip: Range = (-0.2, -0.05)
    undershoot: Range = (-0.3, -0.1)
    swallow_refractory: Range = (2.0, 5.0)
    cues: tuple[str, ...] = ("seal",)
    cue_level: Range = (0.06, 0.14)
    cue_hold: Range = (0.2, 0.6)
    cue_open: Range = (0.2, 0.35)


TRAINING_RANGES = GeneratorRanges()
# Held-out people (heldout_ranges(1.0)): every range moved towards slower, longer, softer and stranger, by
# about half its width or more, so that part of each lies outside the training range (a person's lag or
# time constant cannot be seen in their expressions: beyond the training ranges it is an error no model
# can avoid, and the shift is kept at what tells models apart).
HELDOUT_RANGES = GeneratorRanges(
    lag=(0.1, 0.22), inertia=(0.08, 0.18), second_order=0.5, gain=(0.5, 2.0), jaw_power=(1.3, 1.9),
    saturation=(0.012, 0.022), effort_time=(1.6, 2.5), effort_gain=(0.006, 0.012), signature=(0.0, 1.0),
    swallow_duration=(1.05, 1.3), swallow_amplitude=(0.6, 1.4), dip=(-0.08, 0.0), undershoot=(-0.4, -0.2),
    swallow_refractory=(3.0, 7.0), cue_level=(0.08, 0.17), cue_hold=(0.3, 0.8), cue_open=(0.25, 0.4))


def heldout_ranges(shift: float = 1.0) -> GeneratorRanges:
    """Ranges ``shift`` of the way from :data:`TRAINING_RANGES` to :data:`HELDOUT_RANGES` (0: the training
    generator, 1: the held-out one; each bound interpolated linearly)."""
    values = {}
    for f in dataclasses.fields(GeneratorRanges):
        a, b = getattr(TRAINING_RANGES, f.name), getattr(HELDOUT_RANGES, f.name)
        if f.name == "cues":  # kinds, not a range: the held-out people swallow at the training people's kinds
            values[f.name] = a
        elif isinstance(a, tuple):
            values[f.name] = tuple((1 - shift) * x + shift * y for x, y in zip(a, b))
        else:
            values[f.name] = (1 - shift) * a + shift * b
    return GeneratorRanges(**values)


@dataclass(frozen=True)
class SubjectParams:
    """One synthetic subject: how they move their face and how their larynx follows.

    Expression style: ``neutral`` [55] offsets, ``articulation`` gain, ``syllable_rate`` (Hz),
    ``signature`` [3] the weights of lip press, lower-lip roll and lip closure in their swallow seal
    (sum 1).  Larynx: ``rest`` (tau), ``lag`` (s), ``inertia`` (s) and ``filter_order`` (1 or 2) of the
    articulation low-pass, gains of the articulation terms (tau per unit weight), ``jaw_power``,
    ``saturation`` (tau), ``effort_gain`` (tau) and ``effort_time`` (s), ``swallow_amplitude`` (tau),
    ``swallow_duration`` (s), ``swallow_levels`` [5] (landmark levels of the swallow, fractions of its
    amplitude), ``eta`` (larynx size), ``swallow_refractory`` (s, from a swallow's onset to the earliest next
    one; at least ``swallow_duration``); ``cue`` what their swallows follow (:data:`SWALLOW_CUES`) with its
    ``cue_level``, ``cue_hold`` (s) and ``cue_open`` (:class:`GeneratorRanges`).
    """

    subject: int
    neutral: np.ndarray
    articulation: float
    syllable_rate: float
    signature: np.ndarray
    rest: float
    lag: float
    inertia: float
    filter_order: int
    jaw_gain: float
    spread_gain: float
    round_gain: float
    jaw_power: float
    saturation: float
    effort_gain: float
    effort_time: float
    swallow_amplitude: float
    swallow_duration: float
    swallow_levels: np.ndarray
    eta: float
    swallow_refractory: float
    cue: str = "seal"
    cue_level: float = 0.1
    cue_hold: float = 0.4
    cue_open: float = 0.25


def subject_params(subject: int, seed: int, ranges: GeneratorRanges = TRAINING_RANGES) -> SubjectParams:
    """The parameters of subject ``subject``, a deterministic function of (seed, subject, ranges)."""
    rng = np.random.default_rng([seed, subject, 1])
    neutral = np.zeros(NUM_EXPRESSIONS)
    for name in ("browInnerUp_L", "browInnerUp_R", "mouthSmile_L", "mouthSmile_R", "eyeSquint_L", "eyeSquint_R",
                 "mouthClose", "cheekSquint_L", "cheekSquint_R", "mouthRollUpper"):
        neutral[INDEX[name]] = rng.uniform(0.0, 0.06)
    r = ranges
    gain = float(np.exp(rng.uniform(np.log(r.gain[0]), np.log(r.gain[1]))))
    signature = rng.uniform(*r.signature, 3) + 1e-3
    levels = SWALLOW_LANDMARK_LEVELS.copy()
    levels[1], levels[3] = rng.uniform(*r.dip), rng.uniform(*r.undershoot)
    return SubjectParams(
        subject=subject, neutral=neutral, articulation=rng.uniform(0.75, 1.25), syllable_rate=rng.uniform(4.0, 5.5),
        signature=signature / signature.sum(), rest=rng.normal(0.0, 0.001), lag=rng.uniform(*r.lag),
        inertia=rng.uniform(*r.inertia), filter_order=2 if rng.random() < r.second_order else 1,
        jaw_gain=gain * rng.uniform(0.025, 0.032), spread_gain=gain * rng.uniform(0.015, 0.019),
        round_gain=gain * rng.uniform(0.015, 0.019), jaw_power=rng.uniform(*r.jaw_power),
        saturation=rng.uniform(*r.saturation), effort_gain=rng.uniform(*r.effort_gain),
        effort_time=rng.uniform(*r.effort_time),
        swallow_amplitude=SWALLOW_AMPLITUDE * rng.uniform(*r.swallow_amplitude),
        swallow_duration=SWALLOW_DURATION * rng.uniform(*r.swallow_duration), swallow_levels=levels,
        eta=rng.uniform(0.8, 1.2),
        swallow_refractory=rng.uniform(*r.swallow_refractory),  # drawn after the others: they stay as they were
        cue=str(r.cues[rng.integers(len(r.cues))]), cue_level=rng.uniform(*r.cue_level),
        cue_hold=rng.uniform(*r.cue_hold), cue_open=rng.uniform(*r.cue_open),
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


def _seal(psi: np.ndarray, time: np.ndarray, onset: float, params: SubjectParams, rng) -> None:
    """Draw a swallow's seal into psi [T,55] (in place) from ``onset`` (s): the jaw closes, the subject's
    signature channels press, the chin rises, for about half a second."""
    rise, hold = rng.uniform(0.1, 0.35), rng.uniform(0.3, 0.6)
    envelope = _pulse(time, onset, rise, hold, 0.15)
    seal, chin = rng.uniform(0.5, 0.95), rng.uniform(0.15, 0.65)
    # The seal in the subject's signature: channel c at seal * w_c / |w|^2, so that the response's
    # weighted seal (larynx_response) is `seal`; a little closure and roll whatever the signature.
    press, roll, close = np.minimum(1.0, seal * params.signature / np.sum(params.signature ** 2))
    psi[:, INDEX["jawOpen"]] *= 1 - envelope
    for name, weight in (("mouthPress_L", press), ("mouthPress_R", press * rng.uniform(1.0, 1.1)),
                         ("mouthClose", max(close, 0.1)), ("mouthRollLower", max(roll, 0.1)),
                         ("mouthShrugLower", chin)):
        psi[:, INDEX[name]] = np.maximum(psi[:, INDEX[name]], weight * envelope)


def _band_noise(num_frames: int, fps: float, cutoff: float, rng) -> np.ndarray:
    """Unit-std noise low-passed below ``cutoff`` Hz."""
    x = gaussian_filter1d(rng.standard_normal(num_frames + 64), sigma=fps / (2 * np.pi * cutoff))[32:-32]
    return x / (x.std() + 1e-12)


def generate_expressions(num_frames: int, fps: float, params: SubjectParams, rng: np.random.Generator,
                         swallows_per_minute: float = 8.0, blinks_per_minute: float = 15.0,
                         expression_noise: float = 0.01, repeat_seals: float = 0.4) -> np.ndarray:
    """A talking face: psi [T,55] in [0, 1] at ``fps``.

    ``expression_noise`` is the standard deviation of white tracker noise on every weight;
    ``repeat_seals`` the probability that a swallow's seal is followed 1.2-4 s later by a second seal
    (through speech if need be), which the larynx takes for a swallow only after the subject's refractory
    time (:func:`larynx_response`).
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
        onsets = [rng.uniform(start + 0.1, stop - 0.9)]
        if rng.random() < repeat_seals:
            onsets.append(onsets[0] + rng.uniform(1.2, 4.0))
        for onset in onsets:
            if onset < length - 0.9:
                _seal(psi, time, onset, params, rng)

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


def _low_pass(x: np.ndarray, fps: float, time_constant: float, order: int = 1) -> np.ndarray:
    """``order`` cascaded causal first-order low-passes (exponential smoothing) along axis 0, from rest (0)."""
    a = np.exp(-1.0 / (fps * time_constant))
    for _ in range(order):
        x = lfilter([1 - a], [1, -a], x, axis=0)
    return x


def seal_strength(psi: np.ndarray, params: SubjectParams) -> np.ndarray:
    """The subject's swallow cue [T]: their signature's mix of lip press (the weaker side), lower-lip roll and
    lip closure, times (1 - jawOpen)."""
    press = np.minimum(psi[:, INDEX["mouthPress_L"]], psi[:, INDEX["mouthPress_R"]])
    parts = np.stack([press, psi[:, INDEX["mouthRollLower"]], psi[:, INDEX["mouthClose"]]], axis=1)
    return (parts @ params.signature) * (1 - psi[:, INDEX["jawOpen"]])


def run_length(condition: np.ndarray) -> np.ndarray:
    """bool [T] or [T, C] -> int, same shape: for how many frames up to and including t it has been true."""
    out = np.zeros(condition.shape, np.int32)
    count = np.zeros(condition.shape[1:], np.int32)
    for t, row in enumerate(condition):
        count = np.where(row, count + 1, 0)
        out[t] = count
    return out


def swallow_cue(psi: np.ndarray, fps: float, params: SubjectParams) -> np.ndarray:
    """bool [T]: where the subject's swallow cue (``params.cue``, one of :data:`SWALLOW_CUES`) is on; a swallow
    can start where it switches on.  Causal."""
    if params.cue == "seal":
        return seal_strength(psi, params) >= SWALLOW_SEAL_THRESHOLD
    jaw = np.asarray(psi[:, INDEX["jawOpen"]], np.float64)
    closed = jaw < params.cue_level
    if params.cue == "blink":
        blink = 0.5 * (psi[:, INDEX["eyeBlink_L"]] + psi[:, INDEX["eyeBlink_R"]])
        return (blink > 0.5) & closed
    frames = max(1, int(round(params.cue_hold * fps)))
    if params.cue == "pause":
        return run_length(closed) >= frames
    if params.cue == "snap":
        # the largest jawOpen of frames t-frames+1..t (the window ends at t: causal)
        recent_max = maximum_filter1d(jaw, size=frames, origin=(frames - 1) // 2, mode="nearest")
        return closed & (recent_max > params.cue_open)
    raise ValueError(f"unknown swallow cue '{params.cue}' (expected one of {', '.join(SWALLOW_CUES)})")


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
    posture = params.spread_gain * spread - params.round_gain * rounding - params.jaw_gain * jaw ** params.jaw_power
    posture = params.saturation * np.tanh(posture / params.saturation)  # soft clip: the larynx's range
    articulation = _low_pass(posture, fps, params.inertia, params.filter_order)

    speed = np.abs(np.diff(lagged[:, MOUTH], axis=0, prepend=lagged[:1, MOUTH])).sum(axis=1) * fps
    effort = params.effort_gain * np.tanh(_low_pass(speed, fps, params.effort_time) / 4.0)

    # The swallow reflex follows its cue without the subject's articulation lag.
    cue = swallow_cue(psi, fps, params)
    time = np.arange(num_frames) / fps
    swallows = np.zeros(num_frames)
    crossings = np.flatnonzero(cue[1:] & ~cue[:-1]) + 1
    shape = SwallowShape(levels=params.swallow_levels)
    busy_until = -np.inf
    for frame in crossings:
        if time[frame] < busy_until:
            continue
        amplitude = params.swallow_amplitude * (0.55 + 1.2 * now["mouthShrugLower"][frame])
        swallows += swallow_profile(time, time[frame], params.swallow_duration, amplitude, shape)
        busy_until = time[frame] + max(params.swallow_duration, params.swallow_refractory)
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
                  tau_noise: float = 0.0005, ranges: GeneratorRanges = TRAINING_RANGES,
                  **expression_options) -> LarynxSequence:
    """Sequence ``index`` of ``subject``: deterministic from (seed, subject, index, ranges).

    ``tau_noise`` (tau units) is the standard deviation of white measurement noise on tau, as a tracker adds;
    ``ranges`` those the subject's factors are drawn from; ``expression_options`` go to
    :func:`generate_expressions` (swallows_per_minute, blinks_per_minute, expression_noise, repeat_seals).
    """
    params = subject_params(subject, seed, ranges)
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
