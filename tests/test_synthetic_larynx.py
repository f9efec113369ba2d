"""The synthetic expression -> larynx generator (data/synthetic_larynx.py): people, their larynx responses, the
swallow cues in the face, and the held-out ranges outside the training ones."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from hydra import compose, initialize_config_dir

import tasks  # noqa: F401  (registers the config schemas)
from base.errors import InputError
from data.expressions import EXPRESSION_NAMES
from data.synthetic_larynx import (
    HELDOUT_RANGES,
    HELDOUT_SUBJECT_START,
    SWALLOW_CUES,
    SWALLOW_SEAL_THRESHOLD,
    TRAINING_RANGES,
    generate_expressions,
    heldout_ranges,
    larynx_response,
    make_dataset,
    make_sequence,
    seal_strength,
    split_subjects,
    subject_params,
    swallow_cue,
)
from data.synthetic_tau import SWALLOW_LANDMARK_PHASES

REPO = Path(__file__).resolve().parents[1]
K = {name: k for k, name in enumerate(EXPRESSION_NAMES)}


def data_config(overrides: list[str]):
    """The ``data`` group of ``train.py``'s config (its default: data=synthetic) with ``overrides``."""
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("train", overrides=overrides).data


def test_synthetic_data_deterministic_and_subjects_disjoint():
    train_ids, heldout_ids = split_subjects(5, 3)
    assert not set(train_ids) & set(heldout_ids) and min(heldout_ids) >= HELDOUT_SUBJECT_START
    a, b = make_sequence(3, 1, 300, 30.0, seed=7), make_sequence(3, 1, 300, 30.0, seed=7)
    np.testing.assert_array_equal(a.psi, b.psi)
    np.testing.assert_array_equal(a.tau, b.tau)
    c = make_sequence(3, 1, 300, 30.0, seed=8)
    assert np.abs(c.tau - a.tau).max() > 1e-3
    assert a.psi.shape == (300, 55) and a.psi.min() >= 0 and a.psi.max() <= 1
    dataset = make_dataset(heldout_ids, 2, 10.0, 30.0, seed=7)
    assert len(dataset) == 6 and {s.subject for s in dataset} == {f"s{i}" for i in heldout_ids}


def test_generator_options_come_from_the_config():
    """configs/data_task/larynx_transformer_synthetic.yaml's noise and event rates reach the sequences."""
    from tasks.larynx_transformer import load_sequences

    def data(overrides):
        return data_config(["data.train_subjects=2", "data.sequences_per_subject=1", "data.seconds=60",
                            "data.heldout_subjects=1", "data.heldout_sequences_per_subject=1"] + overrides)

    def noise_free(sequence):
        index = int(sequence.subject[1:])
        return larynx_response(sequence.psi, sequence.fps, subject_params(index, seed=0))

    default, _ = load_sequences(data([]))
    residual = np.concatenate([s.tau - noise_free(s) for s in default])
    assert residual.std() == pytest.approx(0.0005, rel=0.1)  # the config's tau_noise
    idle = K["cheekPuff_L"]  # a weight the generator never drives: tracker noise only (clipped at 0)
    assert all(s.psi[:, idle].max() > 0.02 and s.psi[:, K["eyeBlink_L"]].max() > 0.5 for s in default)
    quiet, _ = load_sequences(data(["data.tau_noise=0", "data.blinks_per_minute=0", "data.expression_noise=0"]))
    for s in quiet:
        np.testing.assert_allclose(s.tau, noise_free(s), atol=1e-6)  # float32 rounding only
        assert s.psi[:, idle].max() == 0.0 and s.psi[:, K["eyeBlink_L"]].max() == 0.0
    busy, _ = load_sequences(data(["data.swallows_per_minute=60"]))
    assert sum(swallow_count(s) for s in busy) > sum(swallow_count(s) for s in default) > 0


def test_swallow_cues_come_from_the_config():
    """data.swallow_cues sets the kinds of cue the people of data=synthetic swallow at, held-out people too; the
    default is the seal alone (the shipped model's data); an unknown kind is refused by name."""
    from tasks.larynx_transformer import SyntheticData, load_sequences, with_cues

    assert {subject_params(i, seed=0, ranges=with_cues(TRAINING_RANGES, SyntheticData())).cue
            for i in range(30)} == {"seal"}
    data = data_config(["data.train_subjects=12", "data.sequences_per_subject=1", "data.seconds=20",
                             "data.heldout_subjects=4", "data.heldout_sequences_per_subject=1", "data.tau_noise=0",
                             "data.swallow_cues=[pause,blink]"])
    train, val = load_sequences(data)
    cues = with_cues(TRAINING_RANGES, SyntheticData(swallow_cues=["pause", "blink"]))
    people = {s.subject: subject_params(int(s.subject[1:]), seed=0, ranges=cues) for s in train}
    assert {p.cue for p in people.values()} == {"pause", "blink"}
    for s in train:  # the sequences' tau is that of people drawn with those cues
        np.testing.assert_allclose(s.tau, larynx_response(s.psi, s.fps, people[s.subject]), atol=1e-6)
    heldout = [s for s in val if int(s.subject[1:]) >= HELDOUT_SUBJECT_START]
    shifted = with_cues(heldout_ranges(1.0), SyntheticData(swallow_cues=["pause", "blink"]))
    for s in heldout:
        person = subject_params(int(s.subject[1:]), seed=0, ranges=shifted)
        assert person.cue in {"pause", "blink"}
        np.testing.assert_allclose(s.tau, larynx_response(s.psi, s.fps, person), atol=1e-6)
    with pytest.raises(InputError, match="data.swallow_cues: cough; expected some of seal, pause, snap, blink"):
        load_sequences(data_config(["data.swallow_cues=[seal,cough]"]))


def swallow_count(sequence) -> int:
    """Seals (the subject's mix of press, roll and closure, jaw closed) crossing the swallow threshold: how
    data.synthetic_larynx starts a swallow."""
    seal = seal_strength(sequence.psi, subject_params(int(sequence.subject[1:]), seed=0)) >= SWALLOW_SEAL_THRESHOLD
    return int(np.sum(seal[1:] & ~seal[:-1]))


def test_larynx_process_is_causal_and_subject_dependent():
    params = subject_params(2, seed=0)
    psi = generate_expressions(600, 30.0, params, np.random.default_rng(0))
    tau = larynx_response(psi, 30.0, params)
    for t in (50, 311, 599):
        np.testing.assert_array_equal(larynx_response(psi[:t], 30.0, params), tau[:t])
    other = larynx_response(psi, 30.0, subject_params(3, seed=0))
    assert np.abs(other - tau).max() > 1e-3


def press_only(params):
    """The subject with the swallow path alone, swallowing at a seal made by lip press only."""
    return dataclasses.replace(params, rest=0.0, effort_gain=0.0, signature=np.array([1.0, 0.0, 0.0]), cue="seal")


def test_swallow_pattern_raises_tau():
    """A lip press with the jaw closed starts a swallow: peak at 40% of its duration, amplitude set by the chin."""
    fps = 30.0
    params = press_only(subject_params(0, seed=0))
    psi = np.zeros((120, 55), np.float32)
    press = np.clip((np.arange(120) - 30) / 10, 0, 1) * 0.8  # ramps 0 -> 0.8 from frame 30 to 40
    psi[:, K["mouthPress_L"]] = psi[:, K["mouthPress_R"]] = press
    psi[:, K["mouthShrugLower"]] = 0.5
    onset = int(np.argmax(press >= SWALLOW_SEAL_THRESHOLD))
    tau = larynx_response(psi, fps, params)
    peak = onset + SWALLOW_LANDMARK_PHASES[2] * params.swallow_duration * fps
    assert abs(np.argmax(tau) - peak) <= 1
    low_chin = psi.copy()
    low_chin[:, K["mouthShrugLower"]] = 0.25
    low_peak = larynx_response(low_chin, fps, params).max()
    assert tau.max() > 1.1 * low_peak  # the chin raise sets the amplitude: higher chin, larger swallow
    assert 0.5 * params.swallow_amplitude < low_peak < tau.max() < 1.5 * params.swallow_amplitude
    assert np.abs(tau[:onset]).max() < 1e-3  # nothing before the press crosses the threshold
    weak = psi.copy()
    weak[:, [K["mouthPress_L"], K["mouthPress_R"]]] = np.minimum(press, 0.9 * SWALLOW_SEAL_THRESHOLD)[:, None]
    assert np.abs(larynx_response(weak, fps, params)).max() < 1e-3  # a bilabial-strength press is no swallow
    # A subject who seals by rolling the lower lip swallows on the roll and not on the press.
    roller = dataclasses.replace(params, signature=np.array([0.0, 1.0, 0.0]))
    assert np.abs(larynx_response(psi, fps, roller)).max() < 1e-3
    rolled = np.zeros_like(psi)
    rolled[:, K["mouthRollLower"]], rolled[:, K["mouthShrugLower"]] = press, 0.5
    np.testing.assert_allclose(larynx_response(rolled, fps, roller), tau, atol=1e-12)


def test_a_seal_within_the_refractory_time_is_no_swallow():
    """Two presses 2.5 s apart: the second is a swallow for a person whose refractory time is 2 s, not for one whose
    refractory time is 4 s; and the generator makes such repeated seals, a share of which the larynx ignores."""
    fps = 30.0
    psi = np.zeros((300, 55), np.float32)
    for start in (30, 105):  # frames: 2.5 s apart
        psi[start:start + 15, K["mouthPress_L"]] = psi[start:start + 15, K["mouthPress_R"]] = 0.8
    psi[:, K["mouthShrugLower"]] = 0.5
    base = press_only(subject_params(0, seed=0))
    quick = larynx_response(psi, fps, dataclasses.replace(base, swallow_refractory=2.0))
    slow = larynx_response(psi, fps, dataclasses.replace(base, swallow_refractory=4.0))
    one = larynx_response(psi[:90], fps, base)  # the first swallow alone, for its size
    second = slice(105, 105 + int(base.swallow_duration * fps))
    assert np.abs(slow[second]).max() < 0.05 * one.max()  # ignored (the first swallow is over by frame 105)
    assert quick[second].max() > 0.8 * one.max()
    suppressed = crossings = 0
    for subject in range(8):
        params = subject_params(subject, seed=0)
        psi = generate_expressions(1800, fps, params, np.random.default_rng(subject))
        seal = seal_strength(psi, params) >= SWALLOW_SEAL_THRESHOLD
        onsets = np.flatnonzero(seal[1:] & ~seal[:-1]) + 1
        gaps = np.diff(onsets) / fps
        crossings += len(onsets)
        suppressed += int(np.sum((gaps > params.swallow_duration) & (gaps < params.swallow_refractory)))
    assert suppressed > 0.2 * crossings, (suppressed, crossings)  # 0.30 here; 0.09 with data.repeat_seals=0


def test_swallows_in_the_expressions_follow_the_signature():
    """Each subject's swallows show in the channels of their signature and reach the seal threshold."""
    for subject in range(6):
        params = subject_params(subject, seed=0)
        psi = generate_expressions(1800, 30.0, params, np.random.default_rng(subject), swallows_per_minute=8.0)
        seal = seal_strength(psi, params)
        assert seal.max() >= SWALLOW_SEAL_THRESHOLD
        strongest = int(np.argmax(params.signature))
        channel = [np.minimum(psi[:, K["mouthPress_L"]], psi[:, K["mouthPress_R"]]), psi[:, K["mouthRollLower"]],
                   psi[:, K["mouthClose"]]][strongest]
        assert channel[seal >= SWALLOW_SEAL_THRESHOLD].mean() > 0.3  # the seal is made of the signature's channel


def onsets_of(cue: np.ndarray) -> list[int]:
    return [int(f) for f in np.flatnonzero(cue[1:] & ~cue[:-1]) + 1]


def test_each_swallow_cue_fires_on_its_own_event_of_the_face():
    """A face that pauses (jaw shut and held), snaps the jaw shut, blinks on an open jaw and on a shut one:
    each cue kind switches on at its event only, and the larynx follows the person's kind."""
    fps = 30.0
    psi = np.zeros((360, 55), np.float32)
    jaw = np.full(360, 0.4)
    jaw[60:90] = 0.02     # a pause of 1 s (closed from 2 s)
    jaw[150:155] = 0.02   # a short closure of 5 frames: a snap shut, no pause
    jaw[240:360] = 0.02   # closed from 8 s on, with a blink at 9 s
    psi[:, K["jawOpen"]] = jaw
    for start in (200, 270):  # blinks at 6.7 s (jaw open) and 9 s (jaw shut)
        psi[start:start + 4, [K["eyeBlink_L"], K["eyeBlink_R"]]] = 0.9
    base = dataclasses.replace(press_only(subject_params(0, seed=0)), cue_level=0.1, cue_hold=0.4, cue_open=0.3,
                               swallow_refractory=2.0)
    expected = {"pause": [60 + 11, 240 + 11], "snap": [60, 150, 240], "blink": [270], "seal": []}
    for cue in SWALLOW_CUES:
        params = dataclasses.replace(base, cue=cue)
        assert onsets_of(swallow_cue(psi, fps, params)) == expected[cue], cue
        swallows = larynx_response(psi, fps, params) - larynx_response(
            psi, fps, dataclasses.replace(params, swallow_amplitude=0.0))
        first = expected[cue][0] if expected[cue] else len(psi)
        assert np.abs(swallows[:first]).max() < 1e-12, cue  # still before the first event
        if expected[cue]:
            assert swallows[first:first + int(params.swallow_duration * fps)].max() > 0.5 * params.swallow_amplitude
    # The snap needs the jaw to have been open past cue_open within cue_hold: not from a half-open jaw.
    lazy = dataclasses.replace(base, cue="snap", cue_open=0.5)
    assert onsets_of(swallow_cue(psi, fps, lazy)) == []
    with pytest.raises(ValueError, match="unknown swallow cue 'cough'"):
        swallow_cue(psi, fps, dataclasses.replace(base, cue="cough"))


def test_people_swallow_at_every_kind_of_cue_they_are_drawn_from():
    """With every cue kind allowed (data.swallow_cues), people are drawn over all of them in about equal shares,
    each with a person's own levels and holds."""
    every = dataclasses.replace(TRAINING_RANGES, cues=SWALLOW_CUES)
    people = [subject_params(i, seed=0, ranges=every) for i in range(40)]
    kinds = {p.cue for p in people}
    assert kinds == set(SWALLOW_CUES)
    for kind in kinds:
        share = np.mean([p.cue == kind for p in people])
        assert 0.1 < share < 0.45, (kind, share)
    levels = [p.cue_level for p in people]
    assert TRAINING_RANGES.cue_level[0] <= min(levels) < max(levels) <= TRAINING_RANGES.cue_level[1]
    assert max(p.cue_hold for p in people) - min(p.cue_hold for p in people) > 0.2


def test_heldout_generator_reaches_outside_the_training_ranges():
    """The validation people of data=synthetic are drawn from shifted ranges (data.heldout_shift): a good part
    of them has a lag, time constant, jaw power, effort time or swallow undershoot no training person has."""
    train = [subject_params(i, seed=0) for i in range(40)]
    held = [subject_params(i, seed=0, ranges=heldout_ranges(1.0)) for i in range(HELDOUT_SUBJECT_START,
                                                                                 HELDOUT_SUBJECT_START + 40)]
    for factor, beyond in (("lag", lambda v, lo, hi: v > hi), ("inertia", lambda v, lo, hi: v > hi),
                           ("jaw_power", lambda v, lo, hi: v < lo), ("effort_time", lambda v, lo, hi: v > hi)):
        values = [getattr(p, factor) for p in train]
        lo, hi = min(values), max(values)
        outside = np.mean([beyond(getattr(p, factor), lo, hi) for p in held])
        assert 0.3 < outside < 1.0, (factor, outside)  # shifted, not disjoint
    undershoots = [p.swallow_levels[3] for p in train]
    assert np.mean([p.swallow_levels[3] < min(undershoots) for p in held]) > 0.2
    assert heldout_ranges(0.0) == TRAINING_RANGES and heldout_ranges(1.0) == HELDOUT_RANGES
    assert heldout_ranges(0.5).lag == pytest.approx((0.065, 0.185))
