"""Anatomical prior of cervical motion (data/cervical_prior.py): statistics, limits, smoothness, loader."""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from conftest import AXIAL_ONE_SIDE, SAGITTAL_TOTAL
from data.cervical_prior import (C1C2, MOTION_KINDS, OC1, PriorConfig, head_rotations, load_theta_sequences,
                                 sample_persons, sample_sequences, segmental_euler)
from data.errors import InputError
from data.files import save_npy
from models.joint_limits import RANGES_DEG, within_limits

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def sequences():
    return sample_sequences(400, seed=11)


def of_kind(sequences, kind):
    return np.degrees(sequences.euler[np.array(sequences.kinds) == kind])


def test_c1c2_carries_about_half_of_large_turns_and_more_of_small_ones(sequences):
    turns = of_kind(sequences, "turn")
    drive = sequences.drives[np.array(sequences.kinds) == "turn"][..., 1]
    axial = turns[..., 1]
    share = axial[..., C1C2] / axial.sum(-1)
    published = AXIAL_ONE_SIDE[C1C2] / AXIAL_ONE_SIDE.sum()  # 0.52
    large = np.median(share[np.abs(drive) > 0.9])
    small = np.median(share[(np.abs(drive) > 0.05) & (np.abs(drive) < 0.3)])
    assert abs(large - published) < 0.08
    assert small > large + 0.1  # C1-C2 moves first (Ishii et al. 2004)


def test_flexion_is_led_by_oc1_and_the_mid_cervical_levels(sequences):
    persons = sample_persons(300, np.random.default_rng(5))
    drives = np.zeros((300, 2, 3))
    drives[:, 0, 0], drives[:, 1, 0] = 1.0, -1.0         # full flexion, full extension, nothing else
    euler = np.degrees(segmental_euler(drives, persons))
    sagittal = (euler[:, 0, :, 0] - euler[:, 1, :, 0]).mean(0)
    # at full drive the split is the published sagittal split
    assert np.abs(sagittal / sagittal.sum() - SAGITTAL_TOTAL / SAGITTAL_TOTAL.sum()).max() < 0.03
    order = list(np.argsort(sagittal)[::-1])
    assert order[0] == OC1 and set(order[2:4]) == {2, 3}  # then C1-C2, then C5-C6 and C4-C5
    nods = np.abs(of_kind(sequences, "nod")[..., 0]).mean((0, 1))
    assert nods.argmax() == OC1                          # small nods are craniocervical
    assert nods[OC1] / nods.sum() > (SAGITTAL_TOTAL[OC1] / SAGITTAL_TOTAL.sum()) + 0.05


def test_lateral_bending_is_subaxial_and_coupled_with_same_side_rotation(sequences):
    tilts = of_kind(sequences, "tilt")
    lateral = np.abs(tilts[..., 2]).mean((0, 1))
    assert lateral[:6].sum() / lateral.sum() > 0.8       # C2-C3 .. C7-T1
    # same side: bending to the right (+az) with rotation to the right (-ay) below C2 (Cook et al. 2006)
    subaxial_axial, subaxial_lateral = tilts[..., :6, 1].ravel(), tilts[..., :6, 2].ravel()
    assert np.corrcoef(subaxial_axial, subaxial_lateral)[0, 1] < -0.9
    slope = np.polyfit(subaxial_lateral, subaxial_axial, 1)[0]
    assert -0.7 < slope < -0.3
    # C1-C2 turns against the subaxial coupled rotation
    assert np.corrcoef(tilts[..., C1C2, 1].ravel(), tilts[..., :6, 1].sum(-1).ravel())[0, 1] < -0.5


def test_turns_couple_upper_cervical_extension_and_contralateral_bending(sequences):
    turns = of_kind(sequences, "turn")
    c1c2_rotation = turns[..., C1C2, 1]
    large = np.abs(c1c2_rotation) > 25
    # Ishii et al. 2004 / Salem et al. 2013: O-C1 extends ~12-13 deg and bends to the other side at full rotation
    assert np.median(turns[..., OC1, 0][large]) < -5
    assert np.median(turns[..., OC1, 2][large] * np.sign(c1c2_rotation[large])) > 1.5


def test_every_pose_is_inside_the_published_limits(sequences):
    theta = torch.tensor(sequences.theta).reshape(-1, 8, 3)
    assert within_limits(theta, tolerance=1e-5).all()
    assert (sequences.persons.ranges_deg <= RANGES_DEG + 1e-9).all()
    scale = sequences.persons.ranges_deg / RANGES_DEG
    assert 0.1 < scale.std() / scale.mean() < 0.3        # per-person variation of the segmental ranges


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


def test_yaml_mirrors_prior_config():
    """configs/data_task/head2neck_synthetic.yaml: the generator's defaults, beside the task's own keys."""
    with open(REPO / "configs" / "data_task" / "head2neck_synthetic.yaml") as f:
        section = yaml.safe_load(f)
    generator = {k: v for k, v in section.items() if k not in ("train_sequences", "val_sequences", "seed", "val_seed")}
    defaults = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(PriorConfig()).items()}
    assert generator == defaults


@pytest.mark.parametrize("field, value", [
    ("fps", 0.0), ("seconds", -1.0), ("range_scale_median", 0.0), ("range_scale_sigma", -0.1),
    ("recruitment_sigma", float("nan")), ("coupling_sigma", -1.0), ("range_scale_min", 0.0),
    ("range_scale_min", 1.5), ("kind_weights", (0.2, 0.2, 0.6)), ("kind_weights", (0.5, -0.1, 0.3, 0.3)),
    ("kind_weights", (0.0, 0.0, 0.0, 0.0)),
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
