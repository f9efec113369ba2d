"""Fitting's application (motion.fit) and what reads its outputs: the fit fields of params.npz, the person's rig,
the training loaders (head2neck data=theta_seq, larynx_transformer data=pairs) on fit folders."""
from __future__ import annotations

import dataclasses
import sys

import numpy as np
import pytest
import torch

from base.errors import InputError
from base.rotations import axis_angle_to_matrix
from data.assets import RigData, with_shape_offset
from data.expressions import EXPRESSION_NAMES
from data.fit_captures import reshaped_person
from data.params import AnimationParams, load_params, rig_checksum, save_params
from models.rig import HeadNeckModel
from scene.characters import person_rig
from scene.gltf import METRES_PER_CM
from tests.blender_sampling import blender_vertices
from tests.conftest import REPO
from tests.test_fbx import blender_ready, gltf_vertex_order

sys.path.insert(0, str(REPO / "benchmarks"))
from fit_app_check import capture_sequence  # noqa: E402  (the synthetic capture, shared with the benchmark)


def fitted_params(rig: HeadNeckModel, frames: int = 20, seed: int = 0, fps: float = 30.0,
                  shape: bool = True) -> AnimationParams:
    """A clip as motion.fit writes it: theta[:, 0] = 0, a swaying placement, eta one value repeated, a residual,
    a smooth shape offset."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / fps
    anatomical = np.zeros((frames, rig.num_joints, 3))
    anatomical[:, 1:, 0] = 0.05 * np.sin(2 * np.pi * 0.7 * t)[:, None]
    anatomical[:, 1:, 1] = 0.04 * np.sin(2 * np.pi * 0.4 * t + 1.0)[:, None]
    theta = rig.from_anatomical(torch.tensor(anatomical, dtype=torch.float32))
    sway = torch.tensor(np.stack([0.1 * np.sin(t), 0.2 * np.cos(t), 0.05 * t], axis=1), dtype=torch.float32)
    with torch.no_grad():
        head = rig.head_rotation(theta).numpy()
    offset = (0.3 * np.sin(rig.rig.template[:, [2, 0, 1]] / 9.0)).astype(np.float32) if shape else None
    return AnimationParams(
        time=t, fps=fps, psi=rng.uniform(0, 0.5, (frames, rig.num_expressions)), tau=0.02 * np.sin(3 * t),
        eta=np.full(frames, 1.1 + 0.1 * seed), theta=theta.numpy(), head_rotation=head,
        joint_names=rig.joint_names, expression_names=rig.expression_names, rig="builtin",
        rig_checksum=rig_checksum(rig.rig), producers={"tool": "motion.fit"},
        root_rotation=axis_angle_to_matrix(sway).numpy(), root_translation=rng.normal(0, 5, (frames, 3)),
        fit_rms_mm=rng.uniform(0.1, 1.0, frames), shape_offset=offset)


# ----------------------------------------------------------------------------- params.npz's fit fields


def test_fit_fields_round_trip_and_default_to_none(tmp_path, builtin_rig):
    params = fitted_params(builtin_rig)
    save_params(tmp_path / "params.npz", params)
    loaded = load_params(tmp_path / "params.npz")
    for name in ("root_rotation", "root_translation", "fit_rms_mm", "shape_offset"):
        assert np.array_equal(getattr(loaded, name), getattr(params, name)), name
    plain = dataclasses.replace(params, root_rotation=None, root_translation=None, fit_rms_mm=None, shape_offset=None)
    save_params(tmp_path / "plain.npz", plain)
    loaded = load_params(tmp_path / "plain.npz")
    assert all(getattr(loaded, n) is None for n in ("root_rotation", "root_translation", "fit_rms_mm", "shape_offset"))
    with np.load(tmp_path / "plain.npz") as z:
        assert "shape_offset" not in z.files


@pytest.mark.parametrize("change, message", [
    ({"root_translation": np.zeros((19, 3))}, r"root_translation has shape \(19, 3\), expected \[20, 3\]"),
    ({"fit_rms_mm": np.zeros((20, 1))}, r"fit_rms_mm has shape \(20, 1\), expected \[20\]"),
    ({"shape_offset": np.zeros((10, 2))}, r"shape_offset has shape \(10, 2\), expected \[10, 3\]"),
    ({"root_rotation": np.tile(2 * np.eye(3), (20, 1, 1))}, r"root_rotation at frame 0 is not a rotation"),
    ({"root_rotation": None}, r"root_rotation and root_translation go together"),
])
def test_fit_fields_are_shape_checked_on_load_and_save(tmp_path, builtin_rig, change, message):
    params = fitted_params(builtin_rig)
    with pytest.raises(ValueError, match=message):
        dataclasses.replace(params, **change)
    stored = {k: v for k, v in vars(params).items() if k not in ("producers", "joint_names", "expression_names")}
    stored.update({k: v for k, v in change.items() if v is not None})
    if change.get("root_rotation", 0) is None:
        del stored["root_rotation"]
    arrays = {k: np.asarray(v) for k, v in stored.items() if v is not None}
    np.savez(tmp_path / "bad.npz", **arrays, joint_names=np.array(params.joint_names),
             expression_names=np.array(params.expression_names))
    with pytest.raises(InputError, match=r"bad\.npz: " + message):
        load_params(tmp_path / "bad.npz")
    params.fit_rms_mm = np.zeros(3)   # changed after construction: refused on save, nothing written
    with pytest.raises(ValueError, match=r"fit_rms_mm has shape \(3,\)"):
        save_params(tmp_path / "later.npz", params)
    assert not (tmp_path / "later.npz").exists()


def test_the_persons_rig_is_the_template_plus_the_offset(builtin_rig):
    offset = np.random.default_rng(1).normal(0, 0.2, builtin_rig.rig.template.shape)
    person = with_shape_offset(builtin_rig.rig, offset)
    assert np.allclose(person.template, builtin_rig.rig.template + offset, atol=1e-5)
    assert person.skin_weights is builtin_rig.rig.skin_weights and with_shape_offset(builtin_rig.rig, None) is \
        builtin_rig.rig
    theta = torch.zeros(1, builtin_rig.num_joints, 3)
    with torch.no_grad():
        moved = HeadNeckModel(person)(theta) - builtin_rig(theta)
    assert np.allclose(moved[0].numpy(), offset, atol=1e-4)    # at rest the offset is what moved
    with pytest.raises(InputError, match=r"fit\.npz: shape_offset of shape \[3, 3\], expected \[5761, 3\]"):
        with_shape_offset(builtin_rig.rig, np.zeros((3, 3)), "fit.npz")


# ----------------------------------------------------------------------------- the loop: training on fits


def test_head2neck_theta_seq_reads_fit_folders_and_checks_the_rig(tmp_path, builtin_rig, turned_rig_file):
    from base.cli import compose_config
    from data.cervical_prior import load_theta_sequences
    from tasks.head2neck import Task

    clips = [fitted_params(builtin_rig, frames=20 + 5 * k, seed=k) for k in range(3)]
    for k, params in enumerate(clips):
        save_params(tmp_path / "fits" / f"take{k}" / "params.npz", params)
    loaded = load_theta_sequences(tmp_path / "fits", rig=builtin_rig.rig)
    assert [len(s.theta) for s in loaded] == [20, 25, 30]
    assert np.array_equal(loaded[2].theta, clips[2].theta)
    single = load_theta_sequences(tmp_path / "fits" / "take1" / "params.npz", rig=builtin_rig.rig)
    assert np.array_equal(single[0].theta, clips[1].theta)
    task = Task(compose_config("train", ["task=head2neck", "data=theta_seq", f"data.path={tmp_path / 'fits'}",
                                         "data.val_fraction=0.34", "data.calibrate=false", "model.hidden=[32,32]"]))
    assert len(task.train["head"]) + len(task.val["head"]) == 75 and len(task.val["head"]) in (20, 25, 30)
    with pytest.raises(InputError, match=r"take0/params\.npz: made with rig 'builtin' .* give rig= the rig"):
        load_theta_sequences(tmp_path / "fits", rig=RigData.load(turned_rig_file))   # what Task passes: its rig=


def test_larynx_pairs_read_a_folder_of_fit_folders_as_takes(tmp_path, builtin_rig):
    from data.pairs import LarynxSequence, load_pairs, save_pair, split_by_take

    clips = {}
    for k, name in enumerate(["anna_walk", "ben_talk", "cleo_swallow"]):
        params = fitted_params(builtin_rig, frames=240, seed=k, shape=False)
        order = np.random.default_rng(k).permutation(len(EXPRESSION_NAMES))   # psi stored in another order
        params = dataclasses.replace(params, psi=params.psi[:, order],
                                     expression_names=[params.expression_names[i] for i in order])
        save_params(tmp_path / "fits" / name / "params.npz", params)
        clips[name] = params
    loose = LarynxSequence(np.full((90, 55), 0.2, np.float32), np.zeros(90, np.float32), 30.0, "dan", "loose_clip01")
    save_pair(tmp_path / "fits" / "loose_clip01.npz", loose)                               # a pair file beside
    pairs = load_pairs(tmp_path / "fits")
    by_take = {p.take: p for p in pairs}
    assert len(pairs) == 4 and {"anna_walk", "ben_talk", "cleo_swallow"} < set(by_take)
    ben = by_take["ben_talk"]
    column = clips["ben_talk"].expression_names.index(EXPRESSION_NAMES[7])
    assert np.array_equal(ben.psi[:, 7], clips["ben_talk"].psi[:, column])
    assert np.array_equal(ben.tau, clips["ben_talk"].tau) and ben.eta == pytest.approx(1.2) and ben.fps == 30.0
    train, val = split_by_take(pairs, 0.25, seed=0)          # what the task does with them (tasks/larynx_transformer)
    assert len(train) == 3 and len(val) == 1


def test_the_loaders_name_a_bad_fit(tmp_path, builtin_rig):
    from data.cervical_prior import load_theta_sequences
    from data.pairs import load_pairs

    (tmp_path / "fits" / "broken").mkdir(parents=True)
    (tmp_path / "fits" / "broken" / "params.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match=r"broken/params\.npz: not a readable \.npz"):
        load_theta_sequences(tmp_path / "fits")
    with pytest.raises(InputError, match=r"broken/params\.npz: not a readable \.npz"):
        load_pairs(tmp_path / "fits")
    (tmp_path / "none").mkdir()
    with pytest.raises(InputError, match=r"none: no \.npz pair files and no fit folders"):
        load_pairs(tmp_path / "none")


# ----------------------------------------------------------------------------- python -m motion.fit


def write_frames(folder, vertices_mm: np.ndarray, faces: np.ndarray) -> None:
    from data.mesh_io import write_ply

    for k, frame in enumerate(vertices_mm):     # frame_2 sorts before frame_10 (natural order)
        write_ply(folder / f"frame_{k}.ply", frame, faces)


def run_fit(argv: list[str]) -> None:
    from base.cli import run_cli
    from motion.fit import run

    run_cli("fit", run, argv)


FAST = ["solver.iterations=[1,1,2]", "progress=false", "threads=1"]   # a short fit: the test checks the tool


def test_motion_fit_ply_meshes_end_to_end(tmp_path, builtin_rig, capsys):
    """4 frames of the built-in rig as PLY in mm, placed far from the rig's frame -> motion.fit -> params.npz:
    theta near the truth (well under the rest pose's error), the world head orientation, tau, the residual
    at the noise; report.json, params.csv and the log say what the issue asks."""
    import json

    truth = capture_sequence(builtin_rig, 4)
    write_frames(tmp_path / "capture", truth["vertices_mm"], builtin_rig.rig.faces)
    out = tmp_path / "fit"
    run_fit([f"input={tmp_path / 'capture'}", "kind=meshes", "units=mm", f"out_dir={out}", "export=[usd]", *FAST])
    log = capsys.readouterr().out
    params = load_params(out / "params.npz")
    assert params.theta.shape == (4, 8, 3) and np.abs(params.theta[:, 0]).max() == 0.0
    from tests.test_usd import baked_error_cm  # USD's own skinning of the fit's anim.usdc against the rig
    assert baked_error_cm(out / "anim.usdc", builtin_rig, params).max() < 0.01
    error = np.degrees(np.linalg.norm(params.theta[:, 1:] - truth["theta"][:, 1:], axis=-1)).mean()
    rest = np.degrees(np.linalg.norm(truth["theta"][:, 1:], axis=-1)).mean()
    assert error < 1.5 and error < 0.2 * rest, (error, rest)
    head = params.root_rotation.astype(np.float64) @ params.head_rotation
    cos = (np.trace(np.swapaxes(head, 1, 2) @ truth["head_world"], axis1=1, axis2=2) - 1) / 2
    assert np.degrees(np.arccos(np.clip(cos, -1, 1))).max() < 0.5
    assert np.abs(params.tau - truth["tau"]).max() < 0.01
    assert 1.0 < params.fit_rms_mm.mean() < 2.5      # 1 mm per axis: about sqrt(3) mm of 3-D residual
    assert params.shape_offset is None and np.allclose(params.eta, params.eta[0])
    assert params.producers["fit"] == "models.fit.fit_meshes" and params.rig == "builtin"
    report = json.loads((out / "report.json").read_text())
    assert report["frames"] == 4 and report["frames_per_s"] > 0 and len(report["worst_frames"]) == 4
    assert report["worst_frames"][0]["rms_mm"] == pytest.approx(params.fit_rms_mm.max(), abs=1e-3)
    assert report["joint_uncertainty_deg"]["c7t1"] is None and report["joint_uncertainty_deg"]["c4c5"] > 0
    header = (out / "params.csv").read_text().splitlines()[0].split(",")
    assert {"fit_rms_mm", "root_tx", "root_rz", "theta_c4c5_x"} <= set(header)
    assert (out / "plot.png").stat().st_size > 10_000
    assert "frames/s" in log and "worst frames: " in log and "joint uncertainty" in log


def test_motion_fit_refuses_bad_input_naming_the_file_and_writes_nothing(tmp_path, builtin_rig, capsys):
    from data.mesh_io import write_ply
    from motion.fit import read_capture

    rest = builtin_rig.rig.template.astype(np.float64) * 10          # mm
    faces = builtin_rig.rig.faces
    cases = {}
    write_frames(tmp_path / "mixed", np.stack([rest, rest]), faces)
    write_ply(tmp_path / "mixed" / "frame_2.ply", rest[:-7], faces[:10])
    cases["mixed"] = (["units=mm"], r"frame_2\.ply: 5754 vertices, the rig has 5761")
    write_frames(tmp_path / "metres", np.stack([rest]), faces)
    cases["metres"] = (["units=m"], r"frame_0\.ply: the capture is .* \d+x the rig's .* units=mm\?")
    write_frames(tmp_path / "nan", np.stack([rest, rest]), faces)
    nan = rest.copy()
    nan[100, 1] = np.nan
    write_ply(tmp_path / "nan" / "frame_1.ply", nan, faces)
    cases["nan"] = (["units=mm"], r"frame_1\.ply: vertex 101 \(byte \d+\) is not finite")
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "frame_0.ply").write_bytes(b"")
    cases["empty"] = (["units=mm"], r"frame_0\.ply: does not start with 'ply'")
    (tmp_path / "none").mkdir()
    cases["none"] = ([], r"none: no \.obj or \.ply files")
    write_frames(tmp_path / "sparse", np.stack([rest, rest]), faces)
    write_ply(tmp_path / "sparse" / "frame_1.ply", rest[::120], np.zeros((0, 3), int))    # 49 points: too few
    cases["sparse"] = (["units=mm", "kind=scans"], r"frame 1 has 49 points, expected at least 100 \(frame 1 is "
                       r"\S*sparse/frame_1\.ply\)")
    np.savez(tmp_path / "take.npz", points=np.zeros((2, 3, 3)))
    cases["take.npz"] = ([], r"take\.npz: no 'vertices' array \(found: points\)")
    for name, (extra, message) in cases.items():
        if name not in ("mixed", "nan", "sparse"):   # the reader's errors; the others through the command line
            units = extra[0].split("=")[1] if extra else "cm"
            with pytest.raises(InputError, match=message):
                read_capture(str(tmp_path / name), "meshes", units, builtin_rig.rig.template)
            continue
        out = tmp_path / f"out_{name}"
        with pytest.raises(SystemExit) as exit_:
            run_fit([f"input={tmp_path / name}", f"out_dir={out}", *extra, *FAST]
                    + ([] if any(e.startswith("kind=") for e in extra) else ["kind=meshes"]))
        err = capsys.readouterr().err
        assert exit_.value.code == 2 and len(err.strip().splitlines()) == 1, (name, err)
        assert __import__("re").search(message, err), (name, err)
        assert not out.exists() and not list(tmp_path.glob(f".out_{name}*")), name   # nothing, not even staging


def test_read_capture_orders_frames_converts_units_and_takes_any_scan(tmp_path, builtin_rig):
    """Frames in natural name order (frame_2 before frame_10), mm -> cm; scans of any count (a front half, in
    ascii PLY and OBJ); an .npz of vertices; a partial scan passes the size check, a scan in the wrong units
    does not."""
    from data.mesh_io import write_obj, write_ply
    from motion.fit import read_capture

    template = builtin_rig.rig.template.astype(np.float64)
    for k in (10, 2, 1):
        write_ply(tmp_path / "meshes" / f"frame_{k}.ply", template * 10 + k, builtin_rig.rig.faces)
    capture = read_capture(str(tmp_path / "meshes"), "meshes", "mm", template)
    assert [n.rsplit("/", 1)[-1] for n in capture.names] == ["frame_1.ply", "frame_2.ply", "frame_10.ply"]
    assert capture.frames.shape == (3, len(template), 3)
    assert np.allclose(capture.frames[2], template + 1.0, atol=1e-4)      # 10 mm = 1 cm
    np.savez(tmp_path / "take.npz", vertices=np.stack([template / 100, template / 100 + 0.01]))
    assert np.allclose(read_capture(str(tmp_path / "take.npz"), "meshes", "m", template).frames[1], template + 1,
                       atol=1e-4)
    front = template[template[:, 2] > np.median(template[:, 2])]
    (tmp_path / "scans").mkdir()
    ascii_body = "".join(f"{x:.4f} {y:.4f} {z:.4f}\n" for x, y, z in front[::2] * 10)
    (tmp_path / "scans" / "a.ply").write_text(f"ply\nformat ascii 1.0\nelement vertex {len(front[::2])}\n"
                                              "property float x\nproperty float y\nproperty float z\nend_header\n"
                                              + ascii_body)
    write_obj(tmp_path / "scans" / "b.obj", front * 10, np.zeros((0, 3), int))
    scans = read_capture(str(tmp_path / "scans"), "scans", "mm", template)
    assert [len(s) for s in scans.frames] == [len(front[::2]), len(front)]
    assert np.allclose(scans.frames[1], front, atol=1e-4)
    with pytest.raises(InputError, match=r"a\.ply: the capture is \d+ cm across with units=cm, [\d.]+x the rig's .*; "
                                         r"units=mm\?"):
        read_capture(str(tmp_path / "scans"), "scans", "cm", template)


# ----------------------------------------------------------------------------- round trip through Blender


def test_a_fitted_person_round_trips_through_the_glb_into_blender(tmp_path, builtin_rig):
    """Issue 55's round trip: another person's capture -> motion.fit (fit_shape) -> params.npz -> anim.glb ->
    Blender's glTF importer, posed at every frame, within 0.01 cm of the fitted mesh (the rig posed on the
    fitted shape) in the rig's frame; without the shape term the same mesh would be centimetres off."""
    if blender_ready() is not None:
        pytest.skip(blender_ready())

    person = HeadNeckModel(reshaped_person(builtin_rig.rig, seed=0))
    truth = capture_sequence(person, 4)
    write_frames(tmp_path / "capture", truth["vertices_mm"], builtin_rig.rig.faces)
    out = tmp_path / "fit"
    run_fit([f"input={tmp_path / 'capture'}", "kind=meshes", "units=mm", "fit_shape=true", f"out_dir={out}",
             "export=[glb]", "plot=false", *FAST])
    params = load_params(out / "params.npz")
    assert params.shape_offset is not None
    frames = np.arange(len(params))
    with torch.no_grad():
        fitted = person_rig(builtin_rig, params)(torch.as_tensor(params.theta), torch.as_tensor(params.psi),
                                                 torch.as_tensor(params.tau), torch.as_tensor(params.eta))
        unshaped = builtin_rig(torch.as_tensor(params.theta), torch.as_tensor(params.psi),
                               torch.as_tensor(params.tau), torch.as_tensor(params.eta))
    order = gltf_vertex_order(builtin_rig)
    blender = blender_vertices(out / "anim.glb", params.fps, frames)["vertices"]          # metres, z up
    in_rig_frame = np.stack([blender[..., 0], blender[..., 2], -blender[..., 1]], axis=-1) / METRES_PER_CM
    error_cm = np.linalg.norm(in_rig_frame - fitted.double().numpy()[:, order], axis=-1)
    assert error_cm.max() < 0.01, f"frame {error_cm.max(1).argmax()}: {error_cm.max():.5f} cm"
    assert np.linalg.norm((fitted - unshaped).numpy(), axis=-1).max() > 0.5   # the shape term is in the file
