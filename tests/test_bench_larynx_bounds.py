"""The swallow bounds of the real-regime benchmark (benchmarks/bench_larynx_bounds.py): the parts of a family's
tau, the hold features and the directly supervised detector on a cue with a known rule."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_larynx_bounds as bounds  # noqa: E402
import larynx_families as families  # noqa: E402

from data.synthetic_larynx import run_length  # noqa: E402


def talking(seed: int, frames: int, open_seconds: tuple[float, float], closed_seconds: tuple[float, float]
            ) -> np.ndarray:
    """psi [frames,55]: the jaw alternating between open (0.3-0.7) and closed (0-0.08) spells of the given
    ranges of length, blinks of 5 frames, every other weight uniform noise in [0, 0.3]."""
    rng = np.random.default_rng(seed)
    psi = rng.uniform(0.0, 0.3, (frames, 55)).astype(np.float32)
    jaw, t, is_open = np.zeros(frames, np.float32), 0, True
    while t < frames:
        low, high = open_seconds if is_open else closed_seconds
        length = max(1, int(rng.uniform(low, high) * families.FPS))
        jaw[t:t + length] = rng.uniform(0.3, 0.7) if is_open else rng.uniform(0.0, 0.08)
        t, is_open = t + length, not is_open
    psi[:, families.K["jawOpen"]] = jaw
    for start in rng.choice(frames - 5, frames // 90, replace=False):  # a blink every 3 s on average
        psi[start:start + 5, [families.K["eyeBlink_L"], families.K["eyeBlink_R"]]] = 0.9
    return psi


def test_a_familys_parts_add_up_to_its_tau_less_the_tracker_noise():
    psi = talking(0, 900, (0.3, 1.5), (0.2, 1.0))
    for family in families.FAMILIES:
        tau = families.family_tau(family, psi, subject=1, seed=2, noise_seed=7)
        parts = families.articulation_part(family, psi, 1, 2) + families.swallow_part(family, psi, 1, 2)
        residual = tau - parts
        assert abs(residual.std() / families.TRACKER_NOISE - 1) < 0.1 and abs(residual.mean()) < 1e-4, family
        assert np.abs(families.swallow_part(family, psi, 1, 2)).max() > 0.01, family  # this psi swallows


def test_run_length_and_the_onset_pulse_of_a_hold():
    condition = np.array([[0], [1], [1], [1], [0], [1]], bool)
    assert run_length(condition)[:, 0].tolist() == [0, 1, 2, 3, 0, 1]
    psi = np.full((40, 55), 0.2, np.float32)
    psi[10:30, families.K["jawOpen"]] = 0.0  # closed from frame 10
    features = bounds.hold_features(psi).reshape(40, -1, 55)[:, :, families.K["jawOpen"]]
    frames = len(bounds.BELOW_FRAMES)
    held_9, onset_9 = features[:, 2], features[:, frames + 2]  # level 0.05, n = 9: the first level's columns
    assert np.flatnonzero(held_9).tolist() == list(range(18, 30))  # the 9th frame of the hold is frame 18
    assert np.flatnonzero(onset_9).tolist() == [18, 19, 20]


def test_the_detector_learns_a_hold_rule_and_finds_it_in_speech_of_another_rhythm():
    """Onsets where the jaw has been closed for 9 frames; trained on one rhythm of talking, tested on
    another (longer openings, shorter closures), with the threshold that gives the training take as many
    detections as onsets: it finds at least 90% of the new take's onsets, with few false ones."""
    def labelled(psi):
        true = families.fire(families.held_for(psi[:, families.K["jawOpen"]] < 0.1, 0.3), 0.0)
        return true, bounds.onset_labels(len(psi), true)

    train = talking(1, 3000, (0.3, 1.5), (0.1, 1.0))
    test = talking(2, 3000, (0.8, 2.5), (0.1, 0.6))
    trained, label = labelled(train)
    features = bounds.hold_features(train)
    probability = bounds.fit_detector(features, label, seed=0, l2=1.0)
    threshold = bounds.count_threshold(probability(features), len(trained), refractory=0.5)
    true, _ = labelled(test)
    found = families.fire(probability(bounds.hold_features(test)) > threshold, 0.5)
    assert len(true) > 20
    assert bounds.hits(found, true) >= 0.9 * len(true), (bounds.hits(found, true), len(true), len(found))
    assert len(found) <= 1.2 * len(true)


def test_hits_pairs_each_onset_once_within_the_tolerance():
    true = np.array([100, 200, 300])
    found = [100 + bounds.MATCH_FRAMES, 102, 205, 300 + bounds.MATCH_FRAMES + 1]
    assert bounds.hits(found, true) == 2  # 100 taken once; 300 missed by a frame


def test_onset_labels_and_density_keep_the_count_and_the_place():
    label = bounds.onset_labels(20, np.array([3, 18]))
    assert np.flatnonzero(label).tolist() == [3, 4, 5, 6, 7, 18, 19]
    density = bounds.onset_density(bounds.onset_labels(40, np.array([10])))
    assert abs(density.sum() - 1) < 1e-9 and np.flatnonzero(density).min() == 10 - bounds.LABEL_FRAMES // 2
