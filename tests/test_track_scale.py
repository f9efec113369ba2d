"""The tracker at an unknown pixel scale (issue 46): the scale estimated from the frames, a wrong one warned about.

Sequences of the built-in rig, talking-free, with head motion, noise and 8-bit quantisation, at 0.5, 1 and 2
times the default 0.08 cm/px over the same view.  The issue's goal for the estimate is 5 %.
"""
from __future__ import annotations

import re

import numpy as np
import pytest
from conftest import SAMPLES_DIR

from base.cli import compose_config
from base.errors import InputError
from base.files import save_npy
from base.tables import CsvTable
from data.fit_captures import PersonConfig, reshaped_person
from models.rig import HeadNeckModel
from motion.track import check_scale, estimate_scale, run, sample_frames
from scene.normal_sequences import SequenceConfig, make_sequence

MOVING = dict(frames=30, noise=0.05, quantize_8bit=True, head_motion_deg=6.0, swallows_per_minute=40.0)


def rendered(rig, cm_per_px: float, seed: int = 0, frames: int = 30):
    """A sequence at ``cm_per_px`` over the view 256 px cover at 0.08 cm/px."""
    return make_sequence(rig, SequenceConfig(**{**MOVING, "frames": frames, "cm_per_px": cm_per_px,
                                                "size": int(round(256 * 0.08 / cm_per_px))}), seed=seed)


@pytest.mark.parametrize("cm_per_px", [0.04, 0.08, 0.16])
def test_the_scale_is_estimated_within_five_percent(builtin_rig, cm_per_px):
    seq = rendered(builtin_rig, cm_per_px, seed=int(cm_per_px * 100))
    estimate = estimate_scale(sample_frames(seq.normals), builtin_rig)
    assert estimate.cm_per_px == pytest.approx(cm_per_px, rel=0.05)
    assert estimate.frames == 5                             # every 6th of the 30 frames


def test_a_neck_filling_the_frame_is_estimated_within_three_percent(builtin_rig):
    """30 px/cm on 256x256 frames: 8.5 cm of neck around the larynx, less than the rig's neck view the estimate
    matches (8.8 x 6.4 cm), no mouth or collarbones in view (issue 57: refused before, or 90 % off on this
    rig)."""
    seq = make_sequence(builtin_rig, SequenceConfig(**{**MOVING, "cm_per_px": 1 / 30, "size": 256}), seed=7)
    assert estimate_scale(sample_frames(seq.normals), builtin_rig).cm_per_px == pytest.approx(1 / 30, rel=0.03)


def test_the_estimate_does_not_depend_on_the_frame_size(builtin_rig):
    """At 0.16 cm/px the 256 px frames show 41 cm (the view's 128 px and much background)."""
    seq = make_sequence(builtin_rig, SequenceConfig(**{**MOVING, "frames": 12, "cm_per_px": 0.16, "size": 256}), seed=3)
    assert estimate_scale(sample_frames(seq.normals), builtin_rig).cm_per_px == pytest.approx(0.16, rel=0.05)


def test_a_wrong_scale_is_warned_about_and_a_right_one_is_not(builtin_rig):
    frames = sample_frames(rendered(builtin_rig, 0.08, seed=5).normals)
    assert check_scale(frames, builtin_rig, 0.08) is None
    assert check_scale(frames, builtin_rig, 0.09) is None             # 12 % off: within the 15 % tolerance
    for given, sign in ((0.16, "+"), (0.04, "-")):
        warning = check_scale(frames, builtin_rig, given)
        assert warning is not None and "\n" not in warning
        assert warning.startswith(f"warning: cm_per_px={given:g} disagrees with the images by {sign}")


def test_frames_that_are_not_a_neck_are_refused(builtin_rig):
    rng = np.random.default_rng(0)
    flat = np.zeros((3, 200, 200, 3), np.float32)
    flat[..., 2] = 1.0
    flat += rng.normal(0.0, 0.05, flat.shape).astype(np.float32)
    flat /= np.linalg.norm(flat, axis=-1, keepdims=True)
    with pytest.raises(InputError, match=r"do not match the rig's neck at any scale .* give cm_per_px=") as error:
        estimate_scale(list(flat), builtin_rig)
    # the message names the scales compared and their scores: 200 px frames showing 6 to 80 cm
    listed = re.findall(r"(\d+\.\d+): (-?\d\.\d\d)", str(error.value).split("cm/px: ", 1)[1])
    scales, scores = np.array(listed, float).T
    assert len(listed) >= 10 and scales.min() < 0.03 and scales.max() > 0.4
    assert np.all(np.diff(scales) > 0) and np.all(np.abs(scores) <= 1.0) and scores.max() < 0.5
    assert check_scale(list(flat), builtin_rig, 0.08) is None         # nothing to compare the given scale with
    with pytest.raises(InputError, match=r"6x6 frames are too small"):          # 3.8 cm at 0.64 cm/px
        estimate_scale([flat[0, :6, :6]], builtin_rig)


def test_cli_without_a_scale_prints_the_estimate_and_calibrates_with_it(tmp_path, builtin_rig, capsys):
    """Frames at 0.12 cm/px: tau (px_per_tau from the rig at the scale used) matches the truth's, which the
    default 0.08 cm/px would put 1.5 times too low."""
    seq = make_sequence(builtin_rig, SequenceConfig(**{**MOVING, "frames": 45, "cm_per_px": 0.12, "size": 171}),
                        seed=2)
    save_npy(tmp_path / "s.npy", seq.normals)
    out = tmp_path / "t.csv"
    run(compose_config("track", [f"input={tmp_path / 's.npy'}", f"out={out}", "plot=null", "progress=false"]))
    captured = capsys.readouterr()
    lines = [line for line in captured.out.splitlines() if line.startswith("scale:")]
    assert len(lines) == 1 and "estimated" in lines[0] and "warning" not in captured.err
    assert float(lines[0].split()[1]) == pytest.approx(0.12, rel=0.05)
    table = CsvTable(out)
    true_tau = seq.tau - seq.tau[0]
    assert np.ptp(true_tau) > 0.03
    assert np.median(np.abs(table.numeric("tau") - true_tau)) < 0.003


def test_cli_warns_about_a_given_scale_twice_the_frames(tmp_path, builtin_rig, capsys):
    seq = rendered(builtin_rig, 0.08, seed=6, frames=12)
    save_npy(tmp_path / "s.npy", seq.normals)
    x, y = seq.larynx_px[0]
    base = [f"input={tmp_path / 's.npy'}", f"out={tmp_path / 't.csv'}", "plot=null", "progress=false",
            f"init_x={x}", f"init_y={y}"]
    run(compose_config("track", [*base, "cm_per_px=0.16"]))          # the given scale is used
    captured = capsys.readouterr()
    warnings = captured.err.strip().splitlines()
    assert len(warnings) == 1 and warnings[0].startswith("warning: cm_per_px=0.16 disagrees with the images by +")
    assert "scale: 0.16 cm/px (given)" in captured.out
    run(compose_config("track", [*base, "cm_per_px=0.08"]))
    assert "warning" not in capsys.readouterr().err


@pytest.mark.shared
def test_another_person_talking_is_estimated_from_the_frames_most_at_rest(real_rig):
    """The real rig reshaped into another person (``data.fit_captures.reshaped_person``: a smooth random field on
    the skin, the neck's width kept), replaying apfel.csv with 6 degrees of head motion, noise 0.08, at 22 px/cm on
    256 px; 15 frames at 5 fps stand for every 6th of 90 at 30 fps.  The peak of the mean correlation curve over
    all frames read +3.5 % (the open jaw reads coarser); the median over the best-matching half +0.9 %."""
    recording = SAMPLES_DIR / "livelinkface" / "apfel.csv"
    if not recording.is_file():
        pytest.skip(f"{recording} not found")
    person = HeadNeckModel(reshaped_person(real_rig.rig, seed=11, config=PersonConfig(neck_width=1.0, head_scale=1.0)))
    config = SequenceConfig(**{**MOVING, "frames": 15, "fps": 5.0, "noise": 0.08, "expressions": str(recording),
                               "cm_per_px": 1 / 22, "size": 256})
    frames = list(make_sequence(person, config, seed=2).normals)
    assert estimate_scale(frames, real_rig).cm_per_px == pytest.approx(1 / 22, rel=0.02)
