"""Head orientation -> cervical spine (models/head2neck.py, tasks/head2neck.py, motion/head2neck.py).

The learning test trains a tiny model on the anatomical prior (a known generating process) and checks
it beats both analytic baselines on sequences of new persons.
"""
from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from hydra import compose, initialize_config_dir
from scipy.spatial.transform import Rotation

import train
from conftest import AXIAL_ONE_SIDE, QUARTER_TURN_X, QUARTER_TURN_Y
from data.cervical_prior import head_rotations, sample_sequences
from data.errors import InputError
from data.files import save_npy, write_csv
from models.checkpoint import load_model
from models.head2neck import (build_model, chain_head_rotation, correct_to_head, head_chain, head_error_deg,
                              predict_theta, split_head_rotation)
from models.joint_limits import within_limits
from models.rotations import (axis_angle_to_matrix, axis_angle_to_quaternion, matrix_to_quaternion,
                              quaternion_to_matrix, relative_angle, ypr_to_matrix)
from motion.head2neck import read_head_rotations, run

REPO = Path(__file__).resolve().parents[1]
CONFIGS = str(REPO / "configs")
C1C2, OC1 = 6, 7


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
    return train.fit(cfg, run_dir), run_dir


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


def test_quaternion_chain_matches_the_rig(builtin_rig, poses):
    theta, head = poses
    rest = matrix_to_quaternion(builtin_rig.anatomical_rest_rotations)
    chain_head, _ = head_chain(axis_angle_to_quaternion(theta[:500]), rest)
    assert torch.allclose(quaternion_to_matrix(chain_head), head[:500], atol=1e-5)
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


def test_predict_theta_refuses_a_model_of_another_rig(builtin_rig, poses):
    model = build_model({"rest_rotations": torch.eye(3).expand(8, 3, 3).tolist(), "hidden": [8],
                         "activation": "silu", "residual_scale": 0.1})
    with pytest.raises(ValueError, match="rest frames differ"):
        predict_theta(model, builtin_rig, poses[1][:4])


def synthetic_data(*overrides):
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        return compose("train", overrides=["task=head2neck", *overrides]).data


def test_synthetic_data_section_is_checked():
    from tasks.head2neck import prior_config

    assert prior_config(synthetic_data("data.coupling_sigma=0.3")).coupling_sigma == 0.3
    with pytest.raises(InputError, match=r"head2neck_synthetic\.yaml\): unknown keys \['coupling_sigmaa'\]"):
        prior_config(synthetic_data("+data.coupling_sigmaa=0.3"))  # a typo is not dropped silently
    with pytest.raises(InputError, match="val_seed equals seed .*validation persons would be the training persons"):
        prior_config(synthetic_data("data.seed=4", "data.val_seed=4"))
    with pytest.raises(InputError, match=r"head2neck_synthetic\.yaml\): range_scale_min must be in \(0, 1\]"):
        prior_config(synthetic_data("data.range_scale_min=1.5"))
    with pytest.raises(InputError, match="val_sequences is 0, expected at least 1"):
        prior_config(synthetic_data("data.val_sequences=0"))


# --------------------------------------------------------------------------- learning


def test_tiny_training_beats_both_baselines_on_new_persons(tiny_run):
    final, run_dir = tiny_run
    assert final["joint_err_deg"] < 0.6 * final["rom_joint_err_deg"]
    assert final["rom_joint_err_deg"] < final["uniform_joint_err_deg"]
    assert final["head_err_max_deg"] < 0.1
    assert final["within_limits"] == 1.0
    assert (run_dir / "checkpoints" / "last.pt").is_file() and (run_dir / "eval.json").is_file()


def test_trained_model_generalises_to_fresh_sequences(tiny_run, builtin_rig, poses):
    theta, head = poses
    model, state = load_model(tiny_run[1] / "checkpoints" / "last.pt", task="head2neck")
    predicted = builtin_rig.to_anatomical(predict_theta(model, builtin_rig, head))  # the prior's frames
    error = torch.rad2deg(relative_angle(axis_angle_to_matrix(predicted), axis_angle_to_matrix(theta))).mean()
    rom = correct_to_head(split_head_rotation(head, model.rest, "rom"), head, builtin_rig)
    rom_error = torch.rad2deg(relative_angle(axis_angle_to_matrix(rom), axis_angle_to_matrix(theta))).mean()
    assert error < 0.6 * rom_error
    assert head_error_deg(predicted, head, builtin_rig).max() < 0.1 and within_limits(predicted).all()


def in_turned_bone_frames(theta: torch.Tensor) -> torch.Tensor:
    """Anatomical theta [...,8,3] -> the bone frames of the conftest ``turned_rig``: a turned bone's axes are
    its anatomical axes times the quarter turn Q, so its rotation vector is Q^T theta (theta @ Q as a row)."""
    bone = theta.clone()
    bone[..., OC1, :] = theta[..., OC1, :] @ torch.tensor(QUARTER_TURN_X, dtype=theta.dtype)
    bone[..., C1C2, :] = theta[..., C1C2, :] @ torch.tensor(QUARTER_TURN_Y, dtype=theta.dtype)
    return bone


def in_turned_bone_frames_matrices(rotations: torch.Tensor) -> torch.Tensor:
    """The same for rotation matrices [...,8,3,3]: Q^T R Q."""
    bone = rotations.clone()
    for joint, turn in ((OC1, QUARTER_TURN_X), (C1C2, QUARTER_TURN_Y)):
        q = torch.tensor(turn, dtype=rotations.dtype)
        bone[..., joint, :, :] = q.T @ rotations[..., joint, :, :] @ q
    return bone


def test_theta_seq_data_in_bone_frames_trains_and_holds_out_whole_files(tmp_path, turned_rig, turned_rig_file):
    """Real sequences are in bone frames (the release's layout); on a rig whose bone frames are not anatomical
    (conftest ``turned_rig``) the task converts them, and the trained model's theta is in bone frames again."""
    from tasks.head2neck import Task

    sequences = sample_sequences(5, seed=7)                       # anatomical frames
    anatomical = torch.tensor(sequences.theta)
    for i, theta in enumerate(in_turned_bone_frames(anatomical)):
        save_npy(tmp_path / "seq" / f"take{i}.npy", theta.numpy())

    def config(path, *extra):
        with initialize_config_dir(config_dir=CONFIGS, version_base=None):
            return compose("train", overrides=[
                "task=head2neck", "data=theta_seq", f"data.path={path}", f"rig={turned_rig_file}",
                "model.hidden=[64]", "trainer.max_steps=150", "trainer.eval_every=0", "trainer.progress=false",
                "trainer.threads=1", *extra])

    one_file = Task(config(tmp_path / "seq" / "take0.npy"))
    assert torch.allclose(one_file.val["rotations"], axis_angle_to_matrix(anatomical[0, 96:]), atol=1e-6)  # last 20%
    assert torch.allclose(one_file.val["head"], head_rotations(turned_rig, anatomical[0, 96:]), atol=1e-6)
    cfg = config(tmp_path / "seq")
    task = Task(cfg)
    assert len(task.val["head"]) == 120 and len(task.train["head"]) == 4 * 120  # 1 of 5 files held out
    (tmp_path / "run").mkdir()
    train.fit(cfg, tmp_path / "run")
    model, _ = load_model(tmp_path / "run" / "checkpoints" / "last.pt", task="head2neck")
    head, truth = task.train["head"], task.train["rotations"]
    bone = predict_theta(model, turned_rig, head)
    assert float(torch.rad2deg(relative_angle(turned_rig.head_rotation(bone), head)).max()) < 0.1
    model_error = torch.rad2deg(relative_angle(axis_angle_to_matrix(bone), in_turned_bone_frames_matrices(truth)))
    rom = correct_to_head(split_head_rotation(head, model.rest, "rom"), head, turned_rig)  # anatomical
    rom_error = torch.rad2deg(relative_angle(axis_angle_to_matrix(rom), truth))
    assert model_error.mean() < 0.8 * rom_error.mean()  # it learnt the files' poses


def test_head_orientation_round_trip_on_turned_bone_frames(builtin_rig, turned_rig, poses):
    """Head orientation of anatomical poses, and predict_theta back to bone frames, on the conftest
    ``turned_rig`` (the built-in rig with oc1 and c1c2 turned: other bone frames, the same anatomy)."""
    theta, head = poses[0][:600], poses[1][:600]  # anatomical; head from the built-in rig (bone = anatomical)
    assert torch.allclose(head_rotations(turned_rig, theta), head, atol=1e-5)
    assert float(head_error_deg(theta, head, turned_rig).max()) < 1e-3
    assert float(head_error_deg(in_turned_bone_frames(theta), head, turned_rig).max()) > 1.0  # bone != anatomical
    # an untrained model is the ROM split plus the exact correction: the same anatomical pose on both rigs
    model = build_model({"rest_rotations": turned_rig.anatomical_rest_rotations.tolist(), "hidden": [8],
                         "activation": "silu", "residual_scale": 0.1})
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
    with initialize_config_dir(config_dir=CONFIGS, version_base=None):
        return compose("head2neck", overrides=[f"{k}={v}" for k, v in overrides.items()])


def test_cli_round_trip_matrices_ypr_and_capture_csv(tiny_run, builtin_rig, poses, tmp_path):
    checkpoint = tiny_run[1] / "checkpoints" / "last.pt"
    head = poses[1][:90].numpy().astype(np.float64)
    save_npy(tmp_path / "rotations.npy", head)
    from_matrices = run(cli_config(checkpoint=checkpoint, input=tmp_path / "rotations.npy",
                                   out=tmp_path / "theta_m.npy", threads=1))
    written = np.load(tmp_path / "theta_m.npy")
    assert written.shape == (90, 8, 3) and written.dtype == np.float32 and np.array_equal(written, from_matrices)
    anatomical = builtin_rig.to_anatomical(torch.tensor(written))
    assert head_error_deg(anatomical, torch.tensor(head, dtype=torch.float32), builtin_rig).max() < 0.1

    ypr = Rotation.from_matrix(head).as_euler("YXZ")  # yaw, pitch, roll of our convention (scipy, independent)
    save_npy(tmp_path / "ypr.npy", np.degrees(ypr))
    from_ypr = run(cli_config(checkpoint=checkpoint, input=tmp_path / "ypr.npy", units="deg",
                              out=tmp_path / "theta_y.npy", threads=1))
    assert np.abs(from_ypr - from_matrices).max() < 1e-3
    save_npy(tmp_path / "ypr_flipped.npy", ypr * [-1, 1, -1])  # a mirrored capture
    flipped = run(cli_config(checkpoint=checkpoint, input=tmp_path / "ypr_flipped.npy", yaw_sign=-1, roll_sign=-1,
                             out=tmp_path / "theta_f.npy", threads=1))
    assert np.abs(flipped - from_matrices).max() < 1e-3

    columns = {"Timecode": [f"10:00:{i // 30:02d}:{i % 30:02d}.000" for i in range(90)],
               "BlendShapeCount": [61] * 90, "JawOpen": np.full(90, 0.2), "EyeBlinkLeft": np.zeros(90),
               "HeadYaw": ypr[:, 0], "HeadPitch": ypr[:, 1], "HeadRoll": ypr[:, 2]}
    write_csv(tmp_path / "take.csv", columns, float_format="%.9f")
    from_csv = run(cli_config(checkpoint=checkpoint, input=tmp_path / "take.csv", out=tmp_path / "theta_c.npy",
                              threads=1))
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


def test_cli_module_end_to_end(tiny_run, poses, tmp_path):
    save_npy(tmp_path / "rotations.npy", poses[1][:30].numpy())
    out = tmp_path / "theta.npy"
    result = subprocess.run([sys.executable, "-m", "motion.head2neck", f"checkpoint={tiny_run[1] / 'checkpoints' / 'last.pt'}",
                             f"input={tmp_path / 'rotations.npy'}", f"out={out}", "threads=1"],
                            cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    assert np.load(out).shape == (30, 8, 3)
    residual = float(result.stdout.split("residual: max ")[1].split(" deg")[0])
    assert residual < 0.1 and "outside the limits: none" in result.stdout
    missing = subprocess.run([sys.executable, "-m", "motion.head2neck", "checkpoint=nowhere.pt",
                              f"input={tmp_path / 'rotations.npy'}", f"out={out}"],
                             cwd=REPO, capture_output=True, text=True, timeout=120)
    assert missing.returncode == 2 and "nowhere.pt: checkpoint not found" in missing.stderr
