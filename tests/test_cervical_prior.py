"""The in-vivo prior of cervical motion (data/cervical_prior/invivo.py): the published kinematics it is built on,
shares that depend on the direction and size of the head motion, coupling, limits, smoothness, loader.

The published figures are typed here from the sources (not read from the module they check).
"""
from __future__ import annotations

import numpy as np
import pytest
import torch
from conftest import AXIAL_ONE_SIDE

from base.errors import InputError
from base.files import save_npy
from data.cervical_prior import (
    C1C2,
    MOTION_KINDS,
    OC1,
    PriorConfig,
    head_rotations,
    load_theta_sequences,
    sample_persons,
    sample_sequences,
    segmental_euler,
)
from data.joint_limits import RANGES_DEG, within_limits

# "In vivo primary and coupled segmental motions of the healthy female head-neck complex during dynamic head
# axial rotation" (J Biomech 2021): one-sided rotation 55.5 deg, C0-C2 71.3 %, C2-T1 18.6 %, coupled bending
# upper contralateral 18.2 deg, lower ipsilateral 21.4 deg.
Z21_TOTAL, Z21_UPPER, Z21_LOWER = 55.5, 71.3, 18.6
Z21_UPPER_BENDING, Z21_LOWER_BENDING = 18.2, 21.4
# Wu et al. (videofluoroscopy, 48 adults), shares of C2-C7 flexion: first third C3/4 29.89 %, C4/5 37.14 %;
# final third up to C5/6 29.45 %, C6/7 37.42 %.
UPPER, LOWER = [C1C2, OC1], list(range(6))
C5T1 = [0, 1, 2]          # C7-T1, C6-C7, C5-C6
C3C5 = [3, 4]             # C4-C5, C3-C4


@pytest.fixture(scope="module")
def sequences():
    return sample_sequences(400, seed=11)


@pytest.fixture(scope="module")
def persons():
    return sample_persons(400, np.random.default_rng(5))


def pure(persons, axis: int, sizes) -> np.ndarray:
    """Segmental Euler angles (degrees) [N,S,J,3] of every person at drives ``sizes`` on one ``axis`` only."""
    drives = np.zeros((len(persons), len(sizes), 3))
    drives[:, :, axis] = sizes
    return np.degrees(segmental_euler(drives, persons))


def of_kind(sequences, kind):
    return np.degrees(sequences.euler[np.array(sequences.kinds) == kind])


# --------------------------------------------------------------------------- axial rotation


def test_turns_are_taken_at_c0_c2_as_measured_in_vivo(persons):
    axial = pure(persons, 1, [1.0])[:, 0, :, 1]                     # full one-sided turns to the left
    upper_share = axial[:, UPPER].sum(-1) / axial.sum(-1)
    assert abs(np.median(upper_share) - Z21_UPPER / (Z21_UPPER + Z21_LOWER)) < 0.06
    # far from the range-of-motion split (C1-C2 holds about half of the published ranges)
    rom_share = AXIAL_ONE_SIDE[[C1C2, OC1]].sum() / AXIAL_ONE_SIDE.sum()
    assert np.median(upper_share) > rom_share + 0.15
    assert 0.7 * Z21_TOTAL < np.median(axial.sum(-1)) < 1.1 * Z21_TOTAL   # inside the persons' envelopes


def test_small_yaws_are_taken_mostly_at_c1c2(persons):
    axial = pure(persons, 1, [0.1, 0.5, 1.0])[..., 1]              # [N,3 sizes,J]
    c1c2_share = np.median(axial[..., C1C2] / axial.sum(-1), axis=0)
    assert c1c2_share[0] > 0.85                                      # ~5 deg: C1-C2 alone, nearly
    assert c1c2_share[0] > c1c2_share[1] > c1c2_share[2]             # its increments shrink (Ishii et al. 2004)


def test_a_turn_bends_the_upper_levels_contralaterally_and_the_lower_ones_ipsilaterally(persons):
    angles = pure(persons, 1, [0.3, -0.3])                           # ~17 deg to the left, then to the right
    for turn, sign in ((angles[:, 0], 1.0), (angles[:, 1], -1.0)):
        head_rotation = turn[..., 1].sum(-1)
        upper_bending = turn[:, UPPER, 2].sum(-1) * sign             # + = to the other side (+az is rightwards)
        lower_bending = turn[:, LOWER, 2].sum(-1) * sign
        assert (upper_bending > 0).mean() > 0.97 and (lower_bending < 0).mean() > 0.97
        # per degree of rotation, as in vivo (small turns: below the published lateral limits)
        upper_ratio, lower_ratio = Z21_UPPER_BENDING / Z21_TOTAL, Z21_LOWER_BENDING / Z21_TOTAL
        assert np.median(upper_bending / np.abs(head_rotation)) == pytest.approx(upper_ratio, rel=0.3)
        assert np.median(-lower_bending / np.abs(head_rotation)) == pytest.approx(lower_ratio, rel=0.3)


def test_turns_keep_the_head_level(sequences):
    """The coupled upper-cervical extension is balanced lower down: a turn's net flexion-extension is small."""
    turns = of_kind(sequences, "turn")
    large = np.abs(turns[..., C1C2, 1]) > 20
    assert np.median(turns[..., OC1, 0][large]) < -1.0                  # O-C1 extends (Ishii 2004, Salem 2013)
    net = np.abs(turns[..., 0].sum(-1)[large])
    assert np.median(net) < 0.25 * np.median(np.abs(turns[..., 1].sum(-1)[large]))


# --------------------------------------------------------------------------- flexion, extension, bending


def test_flexion_spreads_down_the_neck_as_it_grows(persons):
    flexion = pure(persons, 0, [0.15, 0.95])[..., 0]                 # [N,2,J]
    share = np.median(flexion / flexion.sum(-1, keepdims=True), axis=0)
    assert share[1, C5T1].sum() > share[0, C5T1].sum() + 0.1           # the lower levels join late
    assert share[0, C3C5].sum() > share[1, C3C5].sum() + 0.05          # mid-cervical first (Wu et al.)
    c2c7 = slice(1, 6)
    first = flexion[:, 0, c2c7] / flexion[:, 0, c2c7].sum(-1, keepdims=True)
    assert abs(np.median(first[:, 2]) - 0.3714) < 0.08 and abs(np.median(first[:, 3]) - 0.2989) < 0.08
    # the cranial centroid of the flexion moves down the neck (index 0 = C7-T1)
    levels = np.arange(8)
    centroid = (share * levels).sum(-1)
    assert centroid[1] < centroid[0] - 0.3


def test_lateral_bending_is_subaxial_and_coupled_with_same_side_rotation(sequences):
    tilts = of_kind(sequences, "tilt")
    lateral = np.abs(tilts[..., 2]).mean((0, 1))
    assert lateral[:6].sum() / lateral.sum() > 0.75                  # C2-C3 .. C7-T1
    # same side: bending to the right (+az) with rotation to the right (-ay) below C2 (Cook et al. 2006)
    subaxial_axial, subaxial_lateral = tilts[..., :6, 1].ravel(), tilts[..., :6, 2].ravel()
    assert np.corrcoef(subaxial_axial, subaxial_lateral)[0, 1] < -0.8
    # C1-C2 turns against the subaxial coupled rotation (the face stays forward)
    assert np.corrcoef(tilts[..., C1C2, 1].ravel(), tilts[..., :6, 1].sum(-1).ravel())[0, 1] < -0.5


def test_a_shifted_prior_changes_what_it_says(persons):
    """The knobs the shifted-prior tests use: no size dependence gives one split at every size, no coupling
    no bending during a turn."""
    rng = np.random.default_rng(5)
    flat = sample_persons(200, rng, PriorConfig(size_dependence=0.0, share_sigma=0.0))
    flexion = pure(flat, 0, [0.1, 0.6])[..., 0]
    share = flexion / flexion.sum(-1, keepdims=True)
    assert np.abs(share[:, 0] - share[:, 1]).max() < 0.02
    uncoupled = sample_persons(50, rng, PriorConfig(coupling_scale=0.0))
    assert np.abs(pure(uncoupled, 1, [0.5])[..., 2]).max() < 1e-9


# --------------------------------------------------------------------------- envelope, time, seeds


def test_every_pose_is_inside_the_published_limits(sequences):
    theta = torch.tensor(sequences.theta).reshape(-1, 8, 3)
    assert within_limits(theta, tolerance=1e-5).all()
    assert (sequences.persons.ranges_deg <= RANGES_DEG + 1e-9).all()
    scale = sequences.persons.ranges_deg / RANGES_DEG
    assert 0.1 < scale.std() / scale.mean() < 0.3        # per-person variation of the segmental ranges
    spread = sequences.persons.head_range_deg[:, 3]
    assert 0.1 < spread.std() / spread.mean() < 0.3      # [Z21]: 10.8 / 55.5 = 0.19


def test_sequences_are_smooth_at_their_frame_rate(sequences):
    euler = np.degrees(sequences.euler)
    velocity = np.diff(euler, axis=1) * sequences.fps
    acceleration = np.diff(euler, 2, axis=1) * sequences.fps**2
    assert np.abs(velocity).max() < 500                  # deg/s, segmental
    # dominant frequency well below Nyquist: rms(a) / rms(v) = 2 pi f for a sinusoid at f Hz
    assert np.sqrt((acceleration**2).mean() / (velocity**2).mean()) / (2 * np.pi) < 3.0
    fast = sample_sequences(8, seed=3, config=PriorConfig(fps=60.0, seconds=2.0))
    assert fast.theta.shape == (8, 120, 8, 3) and fast.fps == 60.0


def test_kinds_seeds_and_head_orientation(sequences, builtin_rig):
    assert set(sequences.kinds) == set(MOTION_KINDS)
    again = sample_sequences(4, seed=11)
    assert np.array_equal(again.theta, sample_sequences(4, seed=11).theta)
    assert not np.allclose(sample_sequences(4, seed=12).theta, again.theta)
    head = head_rotations(builtin_rig, again.theta)
    assert head.shape == (4, 120, 3, 3)
    direct = builtin_rig.head_rotation(torch.tensor(again.theta[1]))
    assert torch.allclose(head[1], direct, atol=1e-6)


@pytest.mark.parametrize("field, value", [
    ("fps", 0.0), ("seconds", -1.0), ("range_scale_median", 0.0), ("range_scale_sigma", -0.1),
    ("share_sigma", float("nan")), ("coupling_sigma", -1.0), ("range_scale_min", 0.0),
    ("range_scale_min", 1.5), ("head_range_scale", 0.0), ("size_dependence", 2.0), ("coupling_scale", -0.5),
    ("kind_weights", [0.2, 0.2, 0.6]), ("kind_weights", [0.5, -0.1, 0.3, 0.3]), ("kind_weights", [0.0, 0.0, 0.0, 0.0]),
])
def test_prior_config_rejects_values_out_of_range(field, value):
    with pytest.raises(ValueError, match=field):
        PriorConfig(**{field: value})


def test_prior_config_needs_two_frames_per_sequence():
    with pytest.raises(ValueError, match=r"seconds \* fps = 1 frames per sequence, expected at least 2"):
        PriorConfig(fps=10.0, seconds=0.1)
    assert sample_sequences(2, seed=0, config=PriorConfig(fps=10.0, seconds=0.2)).theta.shape == (2, 2, 8, 3)


def test_theta_sequence_loader(tmp_path):
    good = np.zeros((5, 8, 3), np.float32)
    save_npy(tmp_path / "seq" / "b.npy", good + 0.1)
    save_npy(tmp_path / "seq" / "a.npy", good)
    loaded = load_theta_sequences(tmp_path / "seq")
    assert [s.source.rsplit("/", 1)[-1] for s in loaded] == ["a.npy", "b.npy"]
    assert loaded[1].theta.shape == (5, 8, 3) and np.allclose(loaded[1].theta, 0.1)

    save_npy(tmp_path / "wrong.npy", np.zeros((5, 7, 3)))
    with pytest.raises(InputError, match=r"wrong\.npy: array of shape \(5, 7, 3\), expected cervical poses \[T,8,3\]"):
        load_theta_sequences(tmp_path / "wrong.npy")
    degrees = good.copy()
    degrees[2, 4] = [30.0, 0.0, 0.0]
    save_npy(tmp_path / "deg.npy", degrees)
    with pytest.raises(InputError, match=r"deg\.npy: frame 2, joint 4: rotation of 30 rad.*degrees\?"):
        load_theta_sequences(tmp_path / "deg.npy")
    bad = good.copy()
    bad[3, 0, 1] = np.nan
    save_npy(tmp_path / "nan.npy", bad)
    with pytest.raises(InputError, match=r"nan\.npy: non-finite value at index \(3, 0, 1\)"):
        load_theta_sequences(tmp_path / "nan.npy")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty: folder holds no .npy files"):
        load_theta_sequences(tmp_path / "empty")
    (tmp_path / "poses.csv").write_text("0,0,0\n")
    with pytest.raises(InputError, match=r"poses\.csv: unsupported format '\.csv'"):
        load_theta_sequences(tmp_path / "poses.csv")
    with pytest.raises(InputError, match="missing.npy: not found"):
        load_theta_sequences(tmp_path / "missing.npy")
