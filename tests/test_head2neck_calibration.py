"""The default calibration of head -> neck to a recording (tasks/head2neck_calibration.py, issue 58): time
blocks, and the choice between the shipped preset and a calibrated model.

Small settings (three blocks, tens of steps) keep the cross-validation to a few seconds; the benchmark
(``benchmarks/bench_head2neck.py --drift``) runs the defaults.  The data come from generators the presets were
not trained on: a preset's own output moved by a slow drift the head does not show (nothing to learn), and
the uniform split (a clean function of head orientation that neither preset follows)."""
from __future__ import annotations

import numpy as np
import pytest
import torch
from test_head2neck import joint_error, split_corrected, standin_recording

from base.errors import InputError
from base.rotations import axis_angle_to_euler, euler_to_axis_angle
from data.cervical_prior import PriorConfig, head_rotations
from models.head2neck import Head2NeckConfig, correct_to_head, predict_theta
from tasks.head2neck_calibration import CalibrationConfig, calibrate, contiguous_blocks, fold_frames, load_preset

SMALL = CalibrationConfig(folds=3, steps=[10, 40], prior_weights=[0.0], scratch_prior_weights=[], batch_size=32,
                          lr=2e-3, warmup_steps=5)
LOSS = {"lambda_fk": 1.0, "lambda_rot": 1.0, "lambda_sim": 1e-4}


def heads(rig, seed: int) -> torch.Tensor:
    """Every third frame of a stand-in session (167 frames of turns, nods and tilts)."""
    return head_rotations(rig, standin_recording(seed)[::3])


def choose(theta: torch.Tensor, rig):
    return calibrate([theta], rig, Head2NeckConfig(), LOSS, SMALL, PriorConfig(), announce=lambda *_: None)


def test_blocks_are_contiguous_and_cover_the_frames():
    blocks = contiguous_blocks(250, 3)
    assert blocks == [(0, 83), (83, 167), (167, 250)]
    train = fold_frames(250, blocks[1], gap=0.125)                       # 10 frames left out on each side
    assert train.tolist() == list(range(0, 73)) + list(range(177, 250))
    with pytest.raises(InputError, match="5 calibration frames are too few for 3 blocks"):
        contiguous_blocks(5, 3)


def test_drift_alone_keeps_the_preset(builtin_rig):
    """The hack preset's own poses with C1-C2 and the lower levels counter-rotating by a slow drift (4 deg):
    there is nothing in the frames to learn, so the preset is kept untrained."""
    head = heads(builtin_rig, 0)
    hack = load_preset("hack")
    euler = axis_angle_to_euler(builtin_rig.to_anatomical(predict_theta(hack, builtin_rig, head)).double()).numpy()
    drift = np.radians(4.0) * np.sin(np.linspace(0, 5 * np.pi, len(head)) + 0.3)
    euler[:, 6, 1] += drift
    euler[:, 1:6, 1] -= drift[:, None] / 5
    theta = correct_to_head(euler_to_axis_angle(torch.tensor(euler)).float(), head, builtin_rig)
    choice = choose(theta, builtin_rig)
    assert choice.candidate is None and choice.preset == "hack" and choice.steps == 0
    assert choice.model is not None and all(torch.equal(a, b) for a, b in
                                            zip(choice.model.state_dict().values(), hack.state_dict().values()))


def test_train_py_calibrates_to_a_clean_function_of_the_head_in_one_command(tmp_path, builtin_rig):
    """``train.py task=head2neck data=theta_seq data.path=...`` on the uniform split (with the correction) of one
    session's heads, no other setting but the small grid: the calibrated model beats the better preset on the
    held-out blocks and on another session's heads; the loop trains no step, saves it as last.pt and scores it
    on the held-out frames; a fixed ``trainer.max_steps`` is refused with the settings that do what it meant."""
    from base.cli import compose_config
    from base.files import save_npy
    from models.checkpoint import load_model
    from tasks import loop

    head = heads(builtin_rig, 0)
    save_npy(tmp_path / "take.npy", builtin_rig.from_anatomical(split_corrected(head, builtin_rig, "uniform")).numpy())
    small = [f"data.calibration.{key}={value}" for key, value in (
        ("folds", SMALL.folds), ("steps", SMALL.steps), ("prior_weights", SMALL.prior_weights),
        ("scratch_prior_weights", []), ("batch_size", SMALL.batch_size), ("lr", SMALL.lr),
        ("warmup_steps", SMALL.warmup_steps))]
    data = ["task=head2neck", "data=theta_seq", f"data.path={tmp_path / 'take.npy'}", "trainer.progress=false"]
    final = loop.fit(compose_config("train", [*data, *small]), tmp_path / "run")
    assert final["calibration_kept_preset"] == 0.0
    assert final["calibration_heldout_err_deg"] < 0.8 * final["calibration_preset_heldout_err_deg"]
    model, state = load_model(tmp_path / "run" / "checkpoints" / "last.pt", task="head2neck")
    assert state["step"] == 0
    val = head[len(head) - round(0.2 * len(head)):]                                 # the last 20 %: held out
    predicted = builtin_rig.to_anatomical(predict_theta(model, builtin_rig, val))
    assert float(joint_error(predicted, split_corrected(val, builtin_rig, "uniform"))) == pytest.approx(
        final["joint_err_deg"], abs=1e-3)
    other = heads(builtin_rig, 1)
    truth = split_corrected(other, builtin_rig, "uniform")
    calibrated = builtin_rig.to_anatomical(predict_theta(model, builtin_rig, other))
    preset = min(joint_error(builtin_rig.to_anatomical(predict_theta(load_preset(name), builtin_rig, other)), truth)
                 for name in ("default", "hack"))
    assert joint_error(calibrated, truth) < 0.8 * preset
    with pytest.raises(InputError, match=r"trainer\.max_steps=300 with data\.calibrate=true.*data\.steps=300"):
        loop.fit(compose_config("train", [*data, "trainer.max_steps=300", *small]), tmp_path / "refused")
