"""Head orientation -> cervical spine (models/head2neck.py, tasks/head2neck.py, motion/head2neck/__init__.py).

The learning tests train a tiny model on the in-vivo prior (a known generating process) and judge the raw
network (the exact correction makes the head orientation and the limits hold for any output, so they show
nothing about learning): against both analytic baselines on new persons, on a prior shifted from the
training one, with structural probes, and on a stand-in for issue 15's held-back recording drawn from a
different, literature-based generator (:func:`standin_recording`).
"""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from conftest import AXIAL_ONE_SIDE, QUARTER_TURN_X, QUARTER_TURN_Y
from hydra import compose, initialize_config_dir
from scipy.spatial.transform import Rotation

from base.cli import compose_config
from base.errors import InputError
from base.files import save_npy, write_csv
from base.rotations import (
    axis_angle_to_euler,
    axis_angle_to_matrix,
    relative_angle,
    ypr_to_matrix,
)
from data.cervical_prior import PriorConfig, head_rotations, sample_sequences
from data.joint_limits import clamp_to_limits, within_limits
from models.checkpoint import load_model
from models.head2neck import (
    Head2NeckConfig,
    Head2NeckMLP,
    build_model,
    chain_head_rotation,
    correct_to_head,
    head_error_deg,
    predict_theta,
    split_head_rotation,
)
from motion.head2neck import read_head_rotations, run
from tasks import loop

REPO = Path(__file__).resolve().parents[1]
CONFIGS = str(REPO / "configs")
C1C2, OC1 = 6, 7
UPPER, LOWER = [6, 7], list(range(6))


def joint_error(theta: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
    """Mean per-joint angular error (degrees) of anatomical theta [F,8,3] against truth [F,8,3]."""
    return torch.rad2deg(relative_angle(axis_angle_to_matrix(theta), axis_angle_to_matrix(truth))).mean()


def split_corrected(head: torch.Tensor, rig, split: str) -> torch.Tensor:
    return correct_to_head(split_head_rotation(head, rig.anatomical_rest_rotations, split), head, rig)


@pytest.fixture(scope="module")
def poses(builtin_rig):
    """(theta [F,8,3], head [F,3,3]) of prior sequences of persons no training run sees."""
    sequences = sample_sequences(24, seed=99)
    theta = torch.tensor(sequences.theta).reshape(-1, 8, 3)
    return theta, head_rotations(builtin_rig, theta)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    """A tiny training run (hidden 128, 400 steps): (final evaluation, run dir)."""
    run_dir = tmp_path_factory.mktemp("head2neck_run")
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        cfg = compose("train", overrides=[
            "task=head2neck", "model.hidden=[128,128]", "trainer.max_steps=400", "trainer.eval_every=0",
            "trainer.checkpoint_every=400", "trainer.progress=false", "trainer.threads=1",
            "data.train_sequences=192", "data.val_sequences=24", "task.batch_size=512"])
    return loop.fit(cfg, run_dir), run_dir


@pytest.fixture(scope="module")
def tiny_model(tiny_run):
    return load_model(tiny_run[1] / "checkpoints" / "last.pt", task="head2neck")[0]


# --------------------------------------------------------------------------- a stand-in for the recording


def standin_recording(seed: int = 0, frames: int = 500, fps: float = 30.0) -> torch.Tensor:
    """Anatomical theta [frames,8,3] of one subject turning, nodding and tilting (head rotation ~30 deg on
    average, up to ~60), from a generator other than ``data.cervical_prior``'s, built on the literature:

    - axial rotation: per-level angle against head yaw as piecewise-linear curves at 15 deg knots, C1-C2
      saturating (Ishii et al. 2004, upper cervical: 36.2 deg at maximal rotation, O-C1 1.7) and the subaxial
      levels joining late (Ishii et al. 2004, subaxial: 1.5, 1.6, 4.0, 4.6, 4.5, 2.2 deg C7-T1..C2-C3);
    - flexion and extension: incremental shares constant over thirds of the range (Wu et al., C2-C7 thirds;
      upper cervical and C7-T1 shares assumed), lateral bending linear (Lan et al. 2014);
    - coupling per degree of each level's own rotation, from Salem et al. 2013 (another study than the
      prior's): subaxial same-side bending 4.0/5.5, O-C1 and C1-C2 contralateral 5.0/37.5 and 2.5/37.5,
      extension half the supine 12.0/37.5 and 4.0/37.5, balanced at C5-C7; bending -> same-side rotation 0.4;
    - one subject (ranges and a per-level jitter from ``seed``); the levels' rotations are composed as
      rotations (bending, then axial, then sagittal), not added as Euler angles;
    - the session: smooth sweeps through 14 held yaw/pitch/roll targets, a nod and a head shake.
    """
    rng = np.random.default_rng(seed)
    time = np.arange(frames) / fps

    def curves(x, knots, values):
        return np.stack([np.interp(x, knots, values[:, j]) for j in range(values.shape[1])], 1)

    def thirds(shares):  # incremental shares per third -> cumulative fractions at 0, 1/3, 2/3, 1
        shares = np.asarray(shares, float)
        return np.concatenate([np.zeros((1, 8)), np.cumsum(shares / shares.sum(1, keepdims=True) / 3, 0)])

    yaw_knots = np.array([0.0, 15, 30, 45, 60])
    subaxial = np.outer([0, 0.08, 0.3, 0.6, 0.9], [1.5, 1.6, 4.0, 4.6, 4.5, 2.2])
    axial = np.concatenate([subaxial, np.array([[0, 12.5, 22.5, 30.0, 35.0], [0, 0.4, 0.9, 1.3, 1.7]]).T], 1)
    axial[1:] *= (yaw_knots[1:] / axial[1:].sum(1))[:, None]                 # the levels make the head's yaw
    flexion_c2c7 = np.array([[10, 10, 37.14, 29.89, 13], [25, 27, 18, 15, 15], [37.42, 29.45, 12, 11, 10]])
    upper, c7t1 = np.array([0.30, 0.2, 0.1]), np.array([0.02, 0.06, 0.1])
    flexion = thirds(np.concatenate([c7t1[:, None], (1 - upper - c7t1)[:, None] * flexion_c2c7
                                     / flexion_c2c7.sum(1, keepdims=True), upper[:, None] * [[0.75, 0.25]]], 1))
    extension_c2c7 = np.array([[20, 30.21, 20, 15, 15], [18, 26.12, 24.96, 16, 15], [13, 14, 29.77, 27.55, 15]])
    upper, c7t1 = np.array([0.25, 0.3, 0.35]), np.array([0.06, 0.05, 0.04])
    extension = thirds(np.concatenate([c7t1[:, None], (1 - upper - c7t1)[:, None] * extension_c2c7
                                       / extension_c2c7.sum(1, keepdims=True), upper[:, None] * [[0.35, 0.65]]], 1))
    lan = np.array([6.31, 7.19, 8.91, 8.37, 7.66])
    lateral = np.concatenate([[0.07], 0.78 * lan / lan.sum(), [0.08, 0.07]])
    flexion_range, extension_range = 45 * rng.uniform(0.9, 1.1), 60 * rng.uniform(0.9, 1.1)
    jitter = np.exp(rng.normal(0, 0.15, (4, 8)))

    knots = np.linspace(0, time[-1], 14)
    window = np.hanning(15) / np.hanning(15).sum()

    def sweep(targets):
        return np.convolve(np.pad(np.interp(time, knots, targets), 7, mode="edge"), window, "valid")

    yaw = sweep([0, 28, 28, -24, -32, 0, 12, 20, -16, 0, 24, -20, 8, 0])
    yaw += 6 * np.sin(2 * np.pi * 1.3 * time) * (np.abs(time - 9) < 1.2)          # a head shake
    pitch = sweep([0, -12, 24, 30, -18, -36, 6, 24, 24, -30, 18, 6, -24, 0])
    pitch += 5 * np.sin(2 * np.pi * 1.6 * time) * (np.abs(time - 4) < 1.0)        # a nod
    roll = sweep([0, 12, -18, 18, 30, -12, -30, 6, 18, -24, 6, 24, -18, 0])

    a = curves(np.abs(yaw), yaw_knots, axial) * np.sign(yaw)[:, None] * jitter[3]
    thirds_knots = np.linspace(0, 1, 4)
    f = np.where(pitch[:, None] >= 0,
                 flexion_range * curves(np.clip(pitch / flexion_range, 0, 1), thirds_knots, flexion) * jitter[0],
                 -extension_range * curves(np.clip(-pitch / extension_range, 0, 1), thirds_knots, extension)
                 * jitter[1])
    b = roll[:, None] * lateral * jitter[2]
    coupled_b, coupled_f, coupled_a = np.zeros_like(a), np.zeros_like(a), np.zeros_like(a)
    coupled_b[:, :6] = -(4.0 / 5.5) * a[:, :6]
    coupled_b[:, C1C2], coupled_b[:, OC1] = (2.5 / 37.5) * a[:, C1C2], (5.0 / 37.5) * a[:, C1C2]
    c1c2_rotation = np.abs(a[:, C1C2])
    coupled_f[:, OC1], coupled_f[:, C1C2] = -0.5 * (12.0 / 37.5) * c1c2_rotation, -0.5 * (4.0 / 37.5) * c1c2_rotation
    coupled_f[:, 1:3] = 0.25 * (16.0 / 37.5) * np.abs(a[:, C1C2:C1C2 + 1])
    coupled_a[:, :6] = -0.4 * b[:, :6]
    x, y, z = (np.radians(v).reshape(-1) for v in (f + coupled_f, a + coupled_a, b + coupled_b))
    zero = np.zeros_like(x)
    rotation = (Rotation.from_rotvec(np.stack([zero, zero, z], -1))
                * Rotation.from_rotvec(np.stack([zero, y, zero], -1))
                * Rotation.from_rotvec(np.stack([x, zero, zero], -1)))
    return clamp_to_limits(torch.tensor(rotation.as_rotvec().reshape(frames, 8, 3), dtype=torch.float32))


def standin_errors(model, rig, seed: int = 0) -> dict[str, float]:
    """Mean per-joint error (deg) on the stand-in recording: the model (raw and corrected) and the splits."""
    truth = standin_recording(seed)
    head = head_rotations(rig, truth)
    raw = model(head, rig.anatomical_rest_rotations).detach()
    return {"model_raw": float(joint_error(raw, truth)),
            "model": float(joint_error(rig.to_anatomical(predict_theta(model, rig, head)), truth)),
            **{split: float(joint_error(split_corrected(head, rig, split), truth))
               for split in ("uniform", "rom", "invivo")}}


def test_the_standin_recording_resembles_the_held_back_one(builtin_rig):
    """Issue 15 describes the recording: head rotation 30 deg on average, up to 50; per joint (root to head)
    2.0, 3.7, 4.3, 4.4, 4.4, 3.9, 11.1, 3.4 deg; the uniform split is 2.93 deg off.  The stand-in is of that
    kind (same order of magnitude everywhere, C1-C2 the largest), not a copy."""
    truth = standin_recording()
    head = head_rotations(builtin_rig, truth)
    angle = torch.rad2deg(relative_angle(head, torch.eye(3).expand_as(head)))
    assert 25 < float(angle.mean()) < 35 and 45 < float(angle.max()) < 70
    magnitude = torch.rad2deg(truth.norm(dim=-1)).mean(0).numpy()
    recording = np.array([2.0, 3.7, 4.3, 4.4, 4.4, 3.9, 11.1, 3.4])
    assert np.all(magnitude > recording / 2.5) and np.all(magnitude < recording * 2.0)
    assert magnitude.argmax() == C1C2
    assert 2.0 < float(joint_error(split_corrected(head, builtin_rig, "uniform"), truth)) < 5.0


# --------------------------------------------------------------------------- baselines and correction


def test_uniform_split_reproduces_the_head_and_rom_split_follows_published_shares(builtin_rig, poses):
    _, head = poses
    rest = builtin_rig.anatomical_rest_rotations
    uniform = split_head_rotation(head, rest, "uniform")
    assert head_error_deg(uniform, head, builtin_rig).max() < 1e-3
    # a pure turn: each joint's axial share of the bone-frame rotation is its share of the published range
    yaw = torch.tensor([[0.0, math.radians(40.0), 0.0]])
    rom = split_head_rotation(axis_angle_to_matrix(yaw), rest, "rom")
    along_bones = torch.einsum("jkc,k->jc", rest, yaw[0])
    assert np.allclose(rom[0, :, 1] / along_bones[:, 1], AXIAL_ONE_SIDE / AXIAL_ONE_SIDE.sum(), atol=1e-5)
    assert 0.5 < float(head_error_deg(rom, axis_angle_to_matrix(yaw), builtin_rig)) < 10  # not exact


def test_rotation_chain_matches_the_rig(builtin_rig, poses):
    theta, head = poses
    assert torch.allclose(chain_head_rotation(theta[:500], builtin_rig), head[:500], atol=1e-5)


def test_correction_is_exact_and_inside_the_limits(builtin_rig, poses):
    theta, head = poses
    rest = builtin_rig.anatomical_rest_rotations
    for start in (split_head_rotation(head, rest, "rom"),
                  theta + 0.05 * torch.randn(theta.shape, generator=torch.Generator().manual_seed(0))):
        assert head_error_deg(start, head, builtin_rig).max() > 5.0
        assert head_error_deg(correct_to_head(start, head, builtin_rig, iterations=2), head, builtin_rig).max() < 0.1
        corrected = correct_to_head(start, head, builtin_rig, iterations=3)
        assert head_error_deg(corrected, head, builtin_rig).max() < 0.01
        assert within_limits(corrected).all()
    # an exact pose inside the limits is left alone
    assert (correct_to_head(theta, head, builtin_rig) - theta).abs().max() < 1e-4


@pytest.mark.shared
def test_correction_is_exact_on_the_real_rig(real_rig, poses):
    theta = poses[0][:2000]
    head = head_rotations(real_rig, theta)
    assert torch.allclose(chain_head_rotation(theta, real_rig), head, atol=1e-5)  # oc1's frame is turned there
    start = split_head_rotation(head, real_rig.anatomical_rest_rotations, "rom")
    corrected = correct_to_head(start, head, real_rig)
    assert head_error_deg(corrected, head, real_rig).max() < 0.01
    assert within_limits(corrected).all()


def test_the_model_holds_nothing_of_a_rig_and_refuses_another_skeleton(builtin_rig, poses):
    config = {"hidden": [8], "activation": "silu", "residual_scale": 0.1, "base": "invivo", "input_scale": 10.0}
    model = build_model(config)
    assert not any(name.startswith("rest") for name, _ in model.state_dict().items())
    assert sorted(model.state_dict()) == sorted(f"mlp.{i}.{p}" for i in (0, 2) for p in ("weight", "bias"))
    with pytest.raises(InputError, match=r"not the 8-joint cervical chain"):
        predict_theta(model, SimpleNamespace(parents=[-1, 0, 1, 2, 3, 4, 5]), poses[1][:4])
    with pytest.raises(ValueError, match=r"unknown keys \['rest_rotations'\]"):  # a checkpoint of the old layout
        build_model({**config, "rest_rotations": []})
    with pytest.raises(ValueError, match="activation=swish"):
        Head2NeckConfig(activation="swish")


def test_data_section_is_checked():
    """Hydra rejects unknown keys and wrong types; the dataclasses' own checks name the data config file."""
    from tasks.head2neck import SyntheticData, ThetaSeqData, data_config

    def data(*overrides):
        return compose_config("train", ["task=head2neck", *overrides]).data

    section = data_config(data("data.prior.coupling_sigma=0.5"))
    assert isinstance(section, SyntheticData) and section.prior.coupling_sigma == 0.5
    with pytest.raises(InputError, match=r"data\.prior\.coupling_sigmaa"):
        data("data.prior.coupling_sigmaa=0.3")                                 # a typo is not dropped silently
    with pytest.raises(InputError, match=r"head2neck_synthetic\.yaml\): val_seed equals seed .*training persons"):
        data_config(data("data.seed=4", "data.val_seed=4"))
    with pytest.raises(InputError, match=r"head2neck_synthetic\.yaml\): range_scale_min must be in \(0, 1\]"):
        data_config(data("data.prior.range_scale_min=1.5"))
    with pytest.raises(InputError, match="val_sequences is 0, expected at least 1"):
        data_config(data("data.val_sequences=0"))
    mixed = data_config(data("data=theta_seq", "data.path=x.npy", "data.prior_weight=0.25"))
    assert isinstance(mixed, ThetaSeqData) and mixed.prior_weight == 0.25
    with pytest.raises(InputError, match=r"head2neck_theta_seq\.yaml\): prior_weight=1\.0"):
        data_config(data("data=theta_seq", "data.path=x.npy", "data.prior_weight=1.0"))
    with pytest.raises(InputError, match=r"missing data\.path"):
        data("data=theta_seq")


# --------------------------------------------------------------------------- learning (the raw network)


def test_tiny_training_beats_both_baselines_on_new_persons(tiny_run):
    final, run_dir = tiny_run
    assert final["rom_joint_err_deg"] < final["uniform_joint_err_deg"]
    # the raw network, before the correction
    assert final["model_raw_joint_err_deg"] < 0.6 * final["rom_joint_err_deg"]
    assert final["model_raw_joint_err_deg"] < 0.6 * final["invivo_joint_err_deg"]  # the split it starts from
    assert final["model_raw_head_err_mean_deg"] < 0.5 and final["model_raw_within_limits"] > 0.98
    # the exact correction on top
    assert final["joint_err_deg"] < 0.6 * final["rom_joint_err_deg"]
    assert final["head_err_max_deg"] < 0.1 and final["within_limits"] == 1.0
    assert (run_dir / "checkpoints" / "last.pt").is_file() and (run_dir / "eval.json").is_file()


def test_trained_model_generalises_to_fresh_sequences(tiny_model, builtin_rig, poses):
    theta, head = poses
    rest = builtin_rig.anatomical_rest_rotations
    raw = tiny_model(head, rest).detach()
    rom = split_corrected(head, builtin_rig, "rom")
    assert joint_error(raw, theta) < 0.6 * joint_error(rom, theta)
    # the raw network nearly reproduces the head by itself; the split does not
    raw_head, rom_head = head_error_deg(raw, head, builtin_rig), head_error_deg(split_head_rotation(head, rest, "rom"),
                                                                                  head, builtin_rig)
    assert float(raw_head.mean()) < 0.2 * float(rom_head.mean())
    predicted = builtin_rig.to_anatomical(predict_theta(tiny_model, builtin_rig, head))  # the prior's frames
    assert head_error_deg(predicted, head, builtin_rig).max() < 0.1 and within_limits(predicted).all()


def test_model_stays_no_worse_than_the_rom_split_on_a_shifted_prior(tiny_model, builtin_rig):
    """Persons of another prior: smaller ranges and head ranges, weaker size dependence and coupling, more
    spread, another motion mix."""
    shifted = PriorConfig(range_scale_median=0.7, head_range_scale=0.8, size_dependence=0.4, coupling_scale=0.6,
                          share_sigma=0.35, kind_weights=[0.3, 0.3, 0.3, 0.1])
    theta = torch.tensor(sample_sequences(24, seed=321, config=shifted).theta).reshape(-1, 8, 3)
    head = head_rotations(builtin_rig, theta)
    rom = joint_error(split_corrected(head, builtin_rig, "rom"), theta)
    raw = joint_error(tiny_model(head, builtin_rig.anatomical_rest_rotations).detach(), theta)
    corrected = joint_error(builtin_rig.to_anatomical(predict_theta(tiny_model, builtin_rig, head)), theta)
    assert raw <= rom and corrected <= rom
    invivo = joint_error(split_corrected(head, builtin_rig, "invivo"), theta)   # the split the MLP starts from
    assert raw < 0.9 * min(rom, invivo)


def anatomical_prediction(model, rig, ypr_deg) -> np.ndarray:
    """Anatomical Euler angles (deg) [N,8,3] of the model's corrected output for head yaw/pitch/roll (deg)."""
    head = ypr_to_matrix(torch.tensor(np.radians(ypr_deg), dtype=torch.float32))
    return np.degrees(axis_angle_to_euler(rig.to_anatomical(predict_theta(model, rig, head))).numpy())


def test_probe_small_yaws_are_taken_at_c1c2(tiny_model, builtin_rig):
    euler = anatomical_prediction(tiny_model, builtin_rig, [[8.0, 0, 0], [50.0, 0, 0]])[..., 1]
    share = euler[:, C1C2] / euler.sum(-1)
    assert share[0] > 0.8                        # the ROM split gives 0.52, the uniform 0.125
    assert share[1] < share[0] - 0.03            # C1-C2's share falls as the turn grows


def test_probe_a_turn_bends_the_upper_levels_one_way_and_the_lower_levels_the_other(tiny_model, builtin_rig):
    """A 30 deg turn to the left: upper levels bend to the right (+az), lower ones to the left, each by more
    than 0.15 deg per degree of turn (in vivo: 0.33 and 0.39); the split's bending, from the lordosis of the
    joint frames alone, is under 0.05."""
    for sign in (1.0, -1.0):
        euler = anatomical_prediction(tiny_model, builtin_rig, [[30.0 * sign, 0, 0]])[0]
        assert euler[UPPER, 2].sum() * sign > 0.15 * 30 and euler[LOWER, 2].sum() * sign < -0.15 * 30


def test_probe_flexion_spreads_down_the_neck_as_nods_grow(tiny_model, builtin_rig):
    euler = anatomical_prediction(tiny_model, builtin_rig, [[0, 8.0, 0], [0, 35.0, 0]])[..., 0]
    share = euler / euler.sum(-1, keepdims=True)
    assert share[1, [0, 1, 2]].sum() > share[0, [0, 1, 2]].sum() + 0.08   # C5-T1 join as the nod grows
    assert share[0, [3, 4]].sum() > share[1, [3, 4]].sum()                 # C3-C5 lead small nods


def test_model_beats_both_splits_on_the_standin_recording(tiny_model, builtin_rig):
    errors = standin_errors(tiny_model, builtin_rig)
    assert errors["model_raw"] < 0.85 * min(errors["rom"], errors["invivo"]) and errors["rom"] < errors["uniform"]
    assert errors["model"] < 2.0                 # issue 15's goal for the held-back recording


@pytest.mark.shared
def test_model_trained_on_the_builtin_rig_serves_the_real_rig(tiny_model, real_rig, poses):
    theta = poses[0][:3000]
    head = head_rotations(real_rig, theta)
    bone = predict_theta(tiny_model, real_rig, head)
    anatomical = real_rig.to_anatomical(bone)
    assert float(torch.rad2deg(relative_angle(real_rig.head_rotation(bone), head)).max()) < 0.1
    assert within_limits(anatomical).all()
    assert joint_error(tiny_model(head, real_rig.anatomical_rest_rotations).detach(), theta) < \
        0.6 * joint_error(split_corrected(head, real_rig, "rom"), theta)
    errors = standin_errors(tiny_model, real_rig)
    assert errors["model"] < 2.0 and errors["model_raw"] < 0.85 * min(errors["rom"], errors["invivo"])


def shipped_model():
    """The shipped default head2neck model (models/pretrained), or skip when none ships yet."""
    from models.pretrained import load_default, read_manifest

    if "head2neck" not in read_manifest():
        pytest.skip("no shipped head2neck model in models/pretrained yet")
    model, state = load_default("head2neck")
    assert sorted(state["model"]) == sorted(f"mlp.{i}.{p}" for i in (0, 2, 4) for p in ("weight", "bias"))
    assert "config" not in state and "rest_rotations" not in state["model_config"]  # nothing of a rig
    return model


def check_shipped_model_on(rig) -> None:
    model = shipped_model()
    truth = standin_recording()
    head = head_rotations(rig, truth)
    bone = predict_theta(model, rig, head)
    assert float(torch.rad2deg(relative_angle(rig.head_rotation(bone), head)).max()) < 0.01
    assert within_limits(rig.to_anatomical(bone)).all()
    errors = standin_errors(model, rig)
    assert errors["model"] < 2.0 and errors["model_raw"] < 0.85 * min(errors["rom"], errors["invivo"])


def test_the_shipped_model_serves_the_builtin_rig(builtin_rig):
    check_shipped_model_on(builtin_rig)


@pytest.mark.shared
def test_the_shipped_model_serves_the_real_rig(real_rig):
    check_shipped_model_on(real_rig)


# --------------------------------------------------------------------------- real sequences


def in_turned_bone_frames(theta: torch.Tensor) -> torch.Tensor:
    """Anatomical theta [...,8,3] -> the bone frames of the conftest ``turned_rig``: a turned bone's axes are
    its anatomical axes times the quarter turn Q, so its rotation vector is Q^T theta (theta @ Q as a row)."""
    bone = theta.clone()
    bone[..., OC1, :] = theta[..., OC1, :] @ torch.tensor(QUARTER_TURN_X, dtype=theta.dtype)
    bone[..., C1C2, :] = theta[..., C1C2, :] @ torch.tensor(QUARTER_TURN_Y, dtype=theta.dtype)
    return bone


def theta_seq_config(path, rig_file, *extra):
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        return compose("train", overrides=[
            "task=head2neck", "data=theta_seq", f"data.path={path}", f"rig={rig_file}", "model.hidden=[128,128]",
            "data.calibrate=false", "trainer.max_steps=300", "trainer.eval_every=0", "trainer.progress=false",
            "trainer.threads=1", "task.batch_size=256", *extra])


# The users' own captures: persons of another prior than the default one (so what is learnt comes from the files).
USERS = PriorConfig(size_dependence=0.3, coupling_scale=0.5, head_range_scale=0.9, kind_weights=[0.3, 0.3, 0.3, 0.1])


def test_theta_seq_data_in_bone_frames_is_learnt_and_scored_on_a_held_out_file(tmp_path, turned_rig,
                                                                               turned_rig_file):
    """Real sequences are in bone frames (the release's layout); on a rig whose bone frames are not anatomical
    (conftest ``turned_rig``) the task converts them; the model learns the files' poses, judged on a file it
    never saw."""
    from tasks.head2neck import Task

    anatomical = torch.tensor(sample_sequences(6, seed=7, config=USERS).theta)
    for i, theta in enumerate(in_turned_bone_frames(anatomical)):
        save_npy(tmp_path / "seq" / f"take{i}.npy", theta.numpy())
    one_file = Task(theta_seq_config(tmp_path / "seq" / "take0.npy", turned_rig_file))
    assert torch.allclose(one_file.val["rotations"], axis_angle_to_matrix(anatomical[0, 96:]), atol=1e-6)  # last 20%
    assert torch.allclose(one_file.val["head"], head_rotations(turned_rig, anatomical[0, 96:]), atol=1e-6)
    cfg = theta_seq_config(tmp_path / "seq", turned_rig_file, "data.val_fraction=0.17")
    task = Task(cfg)
    assert len(task.val["head"]) == 120 and len(task.train["head"]) == 5 * 120  # 1 of 6 files held out
    held_out = [i for i in range(6) if torch.allclose(task.val["rotations"], axis_angle_to_matrix(anatomical[i]),
                                                     atol=1e-6)]
    assert len(held_out) == 1
    (tmp_path / "run").mkdir()
    final = loop.fit(cfg, tmp_path / "run")
    model, _ = load_model(tmp_path / "run" / "checkpoints" / "last.pt", task="head2neck")
    head, truth = task.val["head"], anatomical[held_out[0]]
    bone = predict_theta(model, turned_rig, head)
    assert float(torch.rad2deg(relative_angle(turned_rig.head_rotation(bone), head)).max()) < 0.1
    rom = split_corrected(head, turned_rig, "rom")                                    # anatomical
    raw = model(head, turned_rig.anatomical_rest_rotations).detach()
    assert joint_error(raw, truth) < 0.8 * joint_error(rom, truth)                     # it learnt the files' poses
    assert joint_error(in_turned_bone_frames(turned_rig.to_anatomical(bone)), in_turned_bone_frames(truth)) \
        == pytest.approx(final["joint_err_deg"], abs=1e-3)                          # eval.json scores that file


def test_theta_seq_mixed_with_the_prior(tmp_path, builtin_rig):
    """``data.prior_weight`` is the share of each batch drawn from the prior; the rest comes from the files."""
    from tasks.head2neck import Task

    anatomical = torch.tensor(sample_sequences(2, seed=8, config=USERS).theta)
    for i, theta in enumerate(anatomical):
        save_npy(tmp_path / "seq" / f"take{i}.npy", theta.numpy())
    task = Task(theta_seq_config(tmp_path / "seq", "null", "data.prior_weight=0.25", "data.prior_sequences=4",
                                 "data.val_fraction=0.5", "task.batch_size=64"))
    assert len(task.prior["head"]) == 4 * 120
    batch = task.batch(0, torch.Generator().manual_seed(0))
    assert len(batch["head"]) == 64

    def rows_in(rows, pool):
        return [bool((pool - row).abs().amax((-1, -2)).min() < 1e-7) for row in rows]

    from_files = batch["head"][:48]
    assert all(rows_in(from_files, task.train["head"])) and not any(rows_in(from_files, task.prior["head"]))
    assert all(rows_in(batch["head"][48:], task.prior["head"]))
    alone = Task(theta_seq_config(tmp_path / "seq", "null", "data.val_fraction=0.5", "task.batch_size=64"))
    assert alone.prior is None and all(rows_in(alone.batch(0, torch.Generator().manual_seed(0))["head"],
                                               alone.train["head"]))


def test_head_orientation_round_trip_on_turned_bone_frames(builtin_rig, turned_rig, poses):
    """Head orientation of anatomical poses, and predict_theta back to bone frames, on the conftest
    ``turned_rig`` (the built-in rig with oc1 and c1c2 turned: other bone frames, the same anatomy)."""
    theta, head = poses[0][:600], poses[1][:600]  # anatomical; head from the built-in rig (bone = anatomical)
    assert torch.allclose(head_rotations(turned_rig, theta), head, atol=1e-5)
    assert float(head_error_deg(theta, head, turned_rig).max()) < 1e-3
    assert float(head_error_deg(in_turned_bone_frames(theta), head, turned_rig).max()) > 1.0  # bone != anatomical
    model = Head2NeckMLP(Head2NeckConfig(hidden=[8]))   # untrained: the in-vivo split plus the exact correction
    bone = predict_theta(model, turned_rig, head)
    assert float(torch.rad2deg(relative_angle(turned_rig.head_rotation(bone), head)).max()) < 0.01
    assert torch.allclose(bone, in_turned_bone_frames(predict_theta(model, builtin_rig, head)), atol=1e-5)


# --------------------------------------------------------------------------- CLI


def test_yaw_pitch_roll_convention():
    deg = math.radians
    face, up = torch.tensor([0.0, 0.0, 1.0]), torch.tensor([0.0, 1.0, 0.0])
    turn, nod, tilt = (ypr_to_matrix(torch.tensor(a)) for a in ([deg(30), 0, 0], [0, deg(20), 0], [0, 0, deg(20)]))
    assert (turn @ face)[0] > 0.49        # face turns to the subject's left (+x)
    assert (nod @ face)[1] < -0.34        # looks down
    assert (tilt @ up)[0] < -0.34         # crown towards the subject's right shoulder (-x)
    ypr = torch.tensor([0.4, -0.2, 0.3])
    expected = Rotation.from_euler("YXZ", ypr.numpy()).as_matrix()  # intrinsic yaw, pitch, roll
    assert np.allclose(ypr_to_matrix(ypr).numpy(), expected, atol=1e-6)


def cli_config(**overrides):
    return compose_config("head2neck", [f"{k}={v}" for k, v in overrides.items()])


def test_cli_round_trip_matrices_ypr_and_capture_csv(tiny_run, builtin_rig, turned_rig, turned_rig_file, poses,
                                                      tmp_path):
    checkpoint = tiny_run[1] / "checkpoints" / "last.pt"
    head = poses[1][:90].numpy().astype(np.float64)
    save_npy(tmp_path / "rotations.npy", head)
    from_matrices = run(cli_config(checkpoint=checkpoint, input=tmp_path / "rotations.npy",
                                   out=tmp_path / "theta_m.npy"))
    written = np.load(tmp_path / "theta_m.npy")
    assert written.shape == (90, 8, 3) and written.dtype == np.float32 and np.array_equal(written, from_matrices)
    anatomical = builtin_rig.to_anatomical(torch.tensor(written))
    assert head_error_deg(anatomical, torch.tensor(head, dtype=torch.float32), builtin_rig).max() < 0.1

    # the same through a rig whose bone frames are not anatomical: theta in its bone frames, the same pose
    turned = run(cli_config(checkpoint=checkpoint, input=tmp_path / "rotations.npy", out=tmp_path / "theta_t.npy",
                            rig=turned_rig_file))
    assert np.abs(turned - in_turned_bone_frames(torch.tensor(from_matrices)).numpy()).max() < 1e-4
    assert float(torch.rad2deg(relative_angle(turned_rig.head_rotation(torch.tensor(turned)),
                                              torch.tensor(head, dtype=torch.float32))).max()) < 0.1

    ypr = Rotation.from_matrix(head).as_euler("YXZ")  # yaw, pitch, roll of our convention (scipy, independent)
    save_npy(tmp_path / "ypr.npy", np.degrees(ypr))
    from_ypr = run(cli_config(checkpoint=checkpoint, input=tmp_path / "ypr.npy", head_units="deg",
                              out=tmp_path / "theta_y.npy"))
    assert np.abs(from_ypr - from_matrices).max() < 1e-3
    save_npy(tmp_path / "ypr_flipped.npy", ypr * [-1, 1, -1])  # a mirrored capture
    flipped = run(cli_config(checkpoint=checkpoint, input=tmp_path / "ypr_flipped.npy", yaw_sign=-1, roll_sign=-1,
                             out=tmp_path / "theta_f.npy"))
    assert np.abs(flipped - from_matrices).max() < 1e-3

    columns = {"Timecode": [f"10:00:{i // 30:02d}:{i % 30:02d}.000" for i in range(90)],
               "BlendShapeCount": [61] * 90, "JawOpen": np.full(90, 0.2), "EyeBlinkLeft": np.zeros(90),
               "HeadYaw": ypr[:, 0], "HeadPitch": ypr[:, 1], "HeadRoll": ypr[:, 2]}
    write_csv(tmp_path / "take.csv", columns, float_format="%.9f")
    from_csv = run(cli_config(checkpoint=checkpoint, input=tmp_path / "take.csv", out=tmp_path / "theta_c.npy"))
    assert np.abs(from_csv - from_matrices).max() < 1e-3


def test_cli_errors_name_the_file_and_frame(tmp_path):
    bad = np.tile(np.eye(3), (4, 1, 1))
    bad[2] *= 2.0
    save_npy(tmp_path / "bad.npy", bad)
    with pytest.raises(InputError, match=r"bad\.npy: frame 2 is not a rotation matrix"):
        read_head_rotations(tmp_path / "bad.npy")
    save_npy(tmp_path / "wide.npy", np.zeros((4, 4)))
    with pytest.raises(InputError, match=r"wide\.npy: array of shape \(4, 4\), expected yaw, pitch, roll \[T,3\]"):
        read_head_rotations(tmp_path / "wide.npy")
    save_npy(tmp_path / "degrees.npy", np.full((4, 3), 30.0))
    with pytest.raises(InputError, match=r"degrees\.npy: angles up to 30 rad after units=rad.*wrong units"):
        read_head_rotations(tmp_path / "degrees.npy")
    frames = 40  # over a second at 30 fps, so the timecode's rate is unambiguous
    write_csv(tmp_path / "nohead.csv", {"Timecode": [f"10:00:{i // 30:02d}:{i % 30:02d}.000" for i in range(frames)],
                                        "JawOpen": np.full(frames, 0.1), "HeadYaw": np.zeros(frames),
                                        "HeadPitch": np.zeros(frames), "HeadRoll": np.zeros(frames)})
    with pytest.raises(InputError, match=r"nohead\.csv: no head rotation recorded"):
        read_head_rotations(tmp_path / "nohead.csv")
    with pytest.raises(InputError, match=r"head_units=turns: expected one of rad, deg, halfturn"):
        run(cli_config(input=tmp_path / "bad.npy", out=tmp_path / "x.npy", head_units="turns"))


def module(*args):
    return subprocess.run([sys.executable, "-m", "motion.head2neck", *args, "threads=1"], cwd=REPO,
                          capture_output=True, text=True, timeout=180)


def test_cli_module_end_to_end_with_halfturns_and_recentring(tiny_run, poses, tmp_path):
    """``head_units=halfturn`` and ``recenter=true`` through the command line: a capture of a subject sitting
    turned 20 deg from the phone, in Unreal's half-turn units, gives the theta of the head's own motion."""
    checkpoint = tiny_run[1] / "checkpoints" / "last.pt"
    head = poses[1][:30].numpy().astype(np.float64)
    relative = np.einsum("ij,tjk->tik", head[0].T, head)                   # H_0^T H_t
    save_npy(tmp_path / "relative.npy", relative)
    expected = run(cli_config(checkpoint=checkpoint, input=tmp_path / "relative.npy", out=tmp_path / "expected.npy"))

    offset = Rotation.from_euler("y", 20, degrees=True).as_matrix()
    captured = np.einsum("ij,tjk->tik", offset, head)                      # M_t = C H_t, H_0 not the rest pose
    ypr = Rotation.from_matrix(captured).as_euler("YXZ") / np.pi          # halfturns: 1 = 180 deg
    save_npy(tmp_path / "captured.npy", ypr)
    out = tmp_path / "theta.npy"
    result = module(f"checkpoint={checkpoint}", f"input={tmp_path / 'captured.npy'}", "input_format=ypr",
                    "head_units=halfturn", "recenter=true", f"out={out}")
    assert result.returncode == 0, result.stderr
    assert np.abs(np.load(out) - expected).max() < 1e-3
    residual = float(result.stdout.split("residual: max ")[1].split(" deg")[0])
    assert residual < 0.1 and "outside the limits: none" in result.stdout
    as_radians = run(cli_config(checkpoint=checkpoint, input=tmp_path / "captured.npy", input_format="ypr",
                                recenter="true", out=tmp_path / "rad.npy"))
    assert np.abs(as_radians - expected).max() > 1e-2                       # the units matter
    not_recentred = run(cli_config(checkpoint=checkpoint, input=tmp_path / "captured.npy", input_format="ypr",
                                   head_units="halfturn", out=tmp_path / "raw.npy"))
    assert np.abs(not_recentred - expected).max() > 1e-2                    # and so does the recentring

    missing = module("checkpoint=nowhere.pt", f"input={tmp_path / 'relative.npy'}", f"out={out}")
    assert missing.returncode == 2 and "nowhere.pt: checkpoint not found" in missing.stderr
    typo = module(f"checkpoint={checkpoint}", f"input={tmp_path / 'relative.npy'}", f"out={out}", "unitz=deg")
    assert typo.returncode == 2 and "unitz" in typo.stderr
