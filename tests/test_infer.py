"""infer.py end to end: a capture -> params.npz / params.csv / plot.png / meshes in one folder.

Expectations are derived independently of infer.py: head orientations from scipy's Euler angles, meshes
from the rig's own forward pass, the swallow from the template file, and (with the shipped models) the
motion of real Live Link Face recordings.
"""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from base.cli import compose_config
from base.errors import InputError
from base.files import write_csv
from data.params import load_params, rig_checksum
from data.synthetic_tau import swallow_profile
from models.checkpoint import save_checkpoint
from models.head2neck import Head2NeckConfig, Head2NeckMLP, model_config
from models.pretrained import read_manifest
from models.rig import HeadNeckModel
from motion.swallow import SwallowTemplate, write_template

REPO = Path(__file__).resolve().parents[1]


def infer(*overrides):
    """infer.py's run on ``overrides``; the synthetic takes here hold a few expression columns only."""
    from infer import run

    if not any(o.startswith("allow_missing=") for o in overrides):
        overrides = (*overrides, "allow_missing=true")
    return run(compose_config("infer", list(overrides)))


def untrained_head2neck(path: Path, rig) -> Path:
    """An untrained head2neck model: the range-of-motion split, made exact by the correction."""
    model = Head2NeckMLP(Head2NeckConfig(hidden=[16, 16]))
    save_checkpoint(path, {"task": "head2neck", "model_config": model_config(model), "model": model.state_dict(),
                           "step": 0})
    return path


def turning_take(path: Path, frames: int = 90) -> tuple[np.ndarray, np.ndarray]:
    time = np.arange(frames) / 30.0
    yaw = 0.4 * np.sin(2 * np.pi * time / 3.0)  # radians: the head turns left and right, pitched down 0.1
    jaw = 0.3 + 0.2 * np.sin(time * 5)
    write_csv(path, {"time": time, "jawOpen": jaw, "HeadYaw": yaw, "HeadPitch": np.full(frames, 0.1),
                     "HeadRoll": np.zeros(frames)}, float_format="%.9g")
    return yaw, jaw


def head_error_deg(rig, theta: np.ndarray, yaw: np.ndarray, pitch: float) -> np.ndarray:
    head = rig.head_rotation(torch.tensor(theta)).numpy()
    target = Rotation.from_euler("YX", np.stack([yaw, np.full(len(yaw), pitch)], 1)).as_matrix()
    return np.degrees(Rotation.from_matrix(np.einsum("tji,tjk->tik", head, target)).magnitude())


@pytest.mark.parametrize("rig_kind", ["builtin", "turned"])
def test_capture_to_output_folder(tmp_path, builtin_rig, turned_rig_file, rig_kind):
    """On the turned-frames rig the bone axes are not the anatomical axes: a missing frame conversion
    would turn the head the wrong way there (and pass on the built-in rig)."""
    rig_file = None if rig_kind == "builtin" else turned_rig_file
    rig = builtin_rig if rig_file is None else HeadNeckModel.load(rig_file)
    yaw, jaw = turning_take(tmp_path / "take.csv")
    out = tmp_path / "out"
    extra = [] if rig_file is None else [f"rig={rig_file}"]
    [row] = infer(f"expressions={tmp_path / 'take.csv'}", f"out_dir={out}", "checkpoint=none",
                  f"head2neck={untrained_head2neck(tmp_path / 'h2n.pt', rig)}", "meshes=true", *extra)
    assert sorted(p.name for p in out.iterdir()) == ["meshes", "params.csv", "params.npz", "plot.png"]
    params = load_params(out / "params.npz")
    assert len(params) == 90 and params.fps == 30.0 and row["frames"] == 90
    assert params.rig_checksum == rig_checksum(rig.rig)
    assert params.theta.shape == (90, 8, 3) and params.joint_names == rig.joint_names
    assert head_error_deg(rig, params.theta, yaw, 0.1).max() < 0.1
    np.testing.assert_allclose(params.psi[:, rig.expression_names.index("jawOpen")], jaw, atol=1e-6)
    np.testing.assert_array_equal(params.tau, 0.0)  # checkpoint=none: the larynx rests
    meshes = sorted((out / "meshes").glob("frame_*.ply"))
    assert len(meshes) == 90
    body = meshes[45].read_bytes().split(b"end_header\n", 1)[1]
    vertices = np.frombuffer(body[: rig.num_vertices * 12], dtype="<f4").reshape(-1, 3)
    psi = torch.zeros(1, 55)
    psi[0, rig.expression_names.index("jawOpen")] = float(jaw[45])
    expected = rig(torch.tensor(params.theta[45:46]), psi)[0].numpy()
    assert np.abs(vertices - expected).max() < 1e-3
    header = (out / "params.csv").read_text().splitlines()[0].split(",")
    assert header[:4] == ["frame", "time", "tau", "eta"] and "theta_oc1_z" in header and "jawOpen" in header


def test_swallow_without_larynx_model_is_the_template(tmp_path):
    turning_take(tmp_path / "take.csv")
    template_time = np.arange(0, 1.2, 1 / 60)
    write_template(tmp_path / "swallow.csv", SwallowTemplate(template_time, swallow_profile(template_time),
                                                             np.zeros_like(template_time), 60.0))
    out = tmp_path / "out"
    infer(f"expressions={tmp_path / 'take.csv'}", f"out_dir={out}", "checkpoint=none", "head2neck=none",
          f"swallow_template={tmp_path / 'swallow.csv'}", "swallow_at=[1.0]", "swallow_playback.blend=add")
    params = load_params(out / "params.npz")
    inside = (params.time >= 1.2) & (params.time <= 1.9)  # past the 0.2 s fades at both ends
    np.testing.assert_allclose(params.tau[inside], swallow_profile(params.time[inside], onset=1.0), atol=1e-6)
    np.testing.assert_array_equal(params.tau[params.time < 1.0], 0.0)


def test_no_head_rotation_recorded_leaves_the_neck_at_rest(tmp_path, builtin_rig, capsys):
    write_csv(tmp_path / "face.csv", {"time": np.arange(30) / 30, "jawOpen": np.full(30, 0.2)})
    out = tmp_path / "out"
    infer(f"expressions={tmp_path / 'face.csv'}", f"out_dir={out}", "checkpoint=none", "plot=false",
          f"head2neck={untrained_head2neck(tmp_path / 'h2n.pt', builtin_rig)}")
    assert "no head rotation recorded" in capsys.readouterr().out
    np.testing.assert_array_equal(load_params(out / "params.npz").theta, 0.0)


def test_folder_of_takes_goes_on_past_a_bad_take(tmp_path):
    takes = tmp_path / "takes"
    takes.mkdir()
    turning_take(takes / "a.csv")
    turning_take(takes / "b.csv", frames=60)
    (takes / "broken.csv").write_text("time,jawOpen\n0.0,0.1\n0.1,abc\n")
    out = tmp_path / "out"
    rows = infer(f"expressions={takes}", f"out_dir={out}", "checkpoint=none", "head2neck=none", "plot=false")
    status = {Path(r["take"]).name: r for r in rows}
    assert status["a.csv"]["status"] == "ok" and status["b.csv"]["frames"] == 60
    assert status["broken.csv"]["status"] == "failed" and "line 3: expected a number" in status["broken.csv"]["reason"]
    assert sorted(p.name for p in out.iterdir()) == ["a", "b", "summary.csv"]
    summary = (out / "summary.csv").read_text()
    assert "broken.csv,failed" in summary.replace(str(takes) + "/", "")


def test_folder_of_takes_in_two_workers_matches_one(tmp_path):
    takes = tmp_path / "takes"
    takes.mkdir()
    for name, frames in (("a", 90), ("b", 45), ("c", 60)):
        turning_take(takes / f"{name}.csv", frames)
    common = [f"expressions={takes}", "checkpoint=none", "head2neck=none", "plot=false"]
    infer(*common, f"out_dir={tmp_path / 'one'}")
    infer(*common, f"out_dir={tmp_path / 'two'}", "workers=2")
    for name in "abc":
        one = load_params(tmp_path / "one" / name / "params.npz")
        two = load_params(tmp_path / "two" / name / "params.npz")
        np.testing.assert_array_equal(one.psi, two.psi)
        np.testing.assert_array_equal(one.time, two.time)


def test_folder_where_every_take_fails_is_an_error(tmp_path):
    takes = tmp_path / "takes"
    takes.mkdir()
    (takes / "x.csv").write_text("")
    with pytest.raises(InputError, match=r"no take could be run"):
        infer(f"expressions={takes}", f"out_dir={tmp_path / 'out'}", "checkpoint=none", "head2neck=none")
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- shipped models, real captures

shipped = pytest.mark.skipif(not {"larynx_transformer", "head2neck"} <= set(read_manifest()),
                             reason="no shipped models in models/pretrained")


@shipped
def test_demo_take_runs_on_a_fresh_clone(tmp_path):
    result = subprocess.run([sys.executable, "infer.py", f"out_dir={tmp_path / 'demo'}"], cwd=REPO,
                            capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr
    assert "built-in demo take" in result.stdout and "the shipped model" in result.stdout
    params = load_params(tmp_path / "demo" / "params.npz")
    assert np.ptp(params.tau) > 0.005  # the larynx moves (0.005 ~ 1.7 mm)
    turn = np.degrees(np.linalg.norm(params.theta[:, :, :], axis=-1)).max()
    assert turn > 3.0  # the 35 degree turn reaches the neck


def with_head_rotation(source: Path, target: Path, yaw_amplitude: float = 0.5) -> np.ndarray:
    """A copy of a Live Link Face take with a head turn written into HeadYaw (radians); returns the yaw per row."""
    lines = source.read_text().splitlines()
    header = lines[0].split(",")
    column = header.index("HeadYaw")
    out, yaws = [lines[0]], []
    for i, line in enumerate(lines[1:]):
        cells = line.split(",")
        if len(cells) == len(header):
            yaw = yaw_amplitude * np.sin(2 * np.pi * i / 300)
            cells[column] = f"{yaw:.6f}"
            yaws.append(yaw)
        out.append(",".join(cells))
    target.write_text("\n".join(out) + "\n")
    return np.array(yaws)


@shipped
def test_real_recordings_with_shipped_models(tmp_path, livelinkface_samples, builtin_rig):
    take = tmp_path / livelinkface_samples[0].name
    with_head_rotation(livelinkface_samples[0], take)
    out = tmp_path / "out"
    infer(f"expressions={take}", f"out_dir={out}", "plot=false", "allow_missing=false")
    params = load_params(out / "params.npz")
    assert len(params) > 1000
    assert np.std(params.tau) > 1e-3  # tau varies with the face
    yaw = np.degrees(Rotation.from_matrix(params.head_rotation).as_euler("YXZ")[:, 0])
    expected = np.degrees(0.5) * np.sin(2 * np.pi * np.arange(len(yaw)) / 300)
    assert np.corrcoef(yaw, expected[: len(yaw)])[0, 1] > 0.9  # theta follows the written turn


def joined_take(samples: list[Path], target: Path) -> int:
    """The recordings end to end as one take (their 60 fps timecodes continued, lost-tracking rows kept)."""
    lines = [samples[0].read_text().splitlines()[0]]
    offset = 0.0
    for sample in samples:
        rows = sample.read_text().splitlines()[1:]
        first = None
        for row in rows:
            code, rest = row.split(",", 1)
            h, m, s, f = code.split(":")
            seconds = int(h) * 3600 + int(m) * 60 + int(s) + float(f) / 60
            first = seconds if first is None else first
            t = offset + seconds - first
            hh, rem = divmod(t, 3600)
            mm, ss = divmod(rem, 60)
            lines.append(f"{int(hh) + 10:02d}:{int(mm):02d}:{int(ss):02d}:{(ss % 1) * 60:06.3f},{rest}")
        offset = t + 2 / 60
    target.write_text("\n".join(lines) + "\n")
    return len(lines) - 1


@shipped
def test_long_joined_recording_with_dropped_frames(tmp_path, livelinkface_samples):
    take = tmp_path / "joined.csv"
    rows = joined_take(livelinkface_samples * 2, take)
    assert rows > 7000
    out = tmp_path / "out"
    [row] = infer(f"expressions={take}", f"out_dir={out}", "plot=false", "allow_missing=false")
    params = load_params(out / "params.npz")
    assert row["status"] == "ok" and len(params) > 3500
    assert np.all(np.diff(params.time) > 0) and np.isfinite(params.tau).all()


def test_exports_land_in_the_output_folder(tmp_path):
    from pygltflib import GLTF2

    turning_take(tmp_path / "take.csv", frames=20)
    out = tmp_path / "out"
    infer(f"expressions={tmp_path / 'take.csv'}", f"out_dir={out}", "checkpoint=none", "head2neck=none", "plot=false",
          "export=[glb,mp4]")
    gltf = GLTF2.load(str(out / "anim.glb"))
    assert len(gltf.animations) == 1 and len(gltf.skins[0].joints) == 8
    times = gltf.accessors[gltf.animations[0].samplers[0].input]
    assert times.count == 20 and abs(times.max[0] - 19 / 30) < 1e-5
    import cv2

    video = cv2.VideoCapture(str(out / "preview.mp4"))
    assert int(video.get(cv2.CAP_PROP_FRAME_COUNT)) == 20 and abs(video.get(cv2.CAP_PROP_FPS) - 30) < 1e-3
    video.release()


def test_character_giraffe_gets_the_motion_at_its_base(tmp_path, builtin_rig):
    """The giraffe's c7t1 (standing in for T1-T2) takes 3x the human flexion, the joints above 0.86x
    (the gains motion.retarget documents); the giraffe's file sits beside its params."""
    from base.rotations import axis_angle_to_euler
    from data.assets import RigData

    time = np.arange(30) / 30.0
    write_csv(tmp_path / "nod.csv", {"time": time, "jawOpen": np.full(30, 0.2), "HeadYaw": np.zeros(30),
                                     "HeadPitch": 0.3 * np.sin(np.pi * time), "HeadRoll": np.zeros(30)})
    out = tmp_path / "out"
    infer(f"expressions={tmp_path / 'nod.csv'}", f"out_dir={out}", "checkpoint=none", "plot=false",
          f"head2neck={untrained_head2neck(tmp_path / 'h2n.pt', builtin_rig)}", "character=giraffe")
    source, target = load_params(out / "source_params.npz"), load_params(out / "params.npz")
    giraffe = HeadNeckModel(RigData.load(out / "character.npz"))
    assert target.rig_checksum == rig_checksum(giraffe.rig) and giraffe.num_vertices == builtin_rig.num_vertices
    with torch.no_grad():
        human_flexion = axis_angle_to_euler(builtin_rig.to_anatomical(torch.tensor(source.theta)))[..., 0]
        giraffe_flexion = axis_angle_to_euler(giraffe.to_anatomical(torch.tensor(target.theta)))[..., 0]
    frame = 15  # the deepest nod
    ratio = (giraffe_flexion[frame] / human_flexion[frame]).numpy()
    np.testing.assert_allclose(ratio[0], 3.0, rtol=0.02)
    np.testing.assert_allclose(ratio[1:], 0.86, rtol=0.02)


def test_one_glb_per_take_serves_the_page_and_blender(tmp_path, builtin_rig, monkeypatch):
    """export=[html,fbx] without glb: the GLB is built once, and the page embeds the very bytes Blender
    converts (Blender stubbed: the test is about what it is handed); the stages are timed by name."""
    import base64
    import re

    import scene.fbx.export as fbx_export
    import scene.gltf.document as document
    from motion.pipeline.config import InferConfig
    from motion.pipeline.models import Models
    from motion.pipeline.outputs import write_outputs
    from tests.test_gltf import clip

    builds, handed = [], []
    real_export_data = document.export_data
    monkeypatch.setattr(document, "export_data", lambda *a, **k: builds.append(1) or real_export_data(*a, **k))
    monkeypatch.setattr(fbx_export, "blender_executable", lambda *a, **k: "blender")

    def fake_blender(command, glb, fbx, *rest, **kwargs):
        handed.append(Path(glb).read_bytes())
        Path(fbx).write_bytes(b"fbx")
        return ""

    monkeypatch.setattr(fbx_export, "run_blender", fake_blender)
    params = clip(builtin_rig, frames=8)
    params.producers = {"source": "take.csv"}
    seconds = write_outputs(InferConfig(plot=False, export=["html", "fbx"]),
                            Models(rig=builtin_rig, rig_name="builtin"), params, tmp_path)
    assert len(builds) == 1 and len(handed) == 1 and handed[0][:4] == b"glTF"
    page = (tmp_path / "viewer.html").read_text()
    assert any(base64.b64decode(chunk) == handed[0] for chunk in re.findall(r"[A-Za-z0-9+/=]{10000,}", page))
    assert list(seconds) == ["write", "glb", "html", "fbx"] and all(v >= 0 for v in seconds.values())
    assert not (tmp_path / "anim.glb").exists() and (tmp_path / "anim.fbx").read_bytes() == b"fbx"
