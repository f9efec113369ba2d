"""Rig files: conversion from the release layout, errors on bad asset folders, mesh writers."""
from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from release_layout import write_release

from base.errors import InputError
from data.assets import RigData, convert
from data.mesh_io import read_obj, triangulate, write_obj, write_ply
from models.rig import HeadNeckModel


@pytest.fixture(scope="module")
def release(tmp_path_factory, builtin_rig):
    root = tmp_path_factory.mktemp("release")
    write_release(builtin_rig.rig, root / "HACK-Model", root / "ICT-FaceKit")
    return root


def test_conversion_reproduces_the_rig(release, builtin_rig, tmp_path):
    out = tmp_path / "rig.npz"
    convert(release / "HACK-Model", release / "ICT-FaceKit", out)
    converted = HeadNeckModel.load(out)
    assert converted.num_larynx_maps == 1 and converted.num_shapes == 0
    g = torch.Generator().manual_seed(0)
    theta = (torch.rand(4, 8, 3, generator=g) - 0.5) * 0.6
    psi = torch.rand(4, 55, generator=g)
    tau = (torch.rand(4, generator=g) - 0.5) * 0.1
    eta = torch.rand(4, generator=g) * 2
    expected = builtin_rig(theta, psi, tau, eta)  # first larynx map, no shape: what the release can hold
    assert (converted(theta, psi, tau, eta) - expected).abs().max() < 1e-4


def test_rig_file_round_trip_keeps_every_array(builtin_rig, tmp_path):
    builtin_rig.rig.save(tmp_path / "builtin.npz")
    loaded = RigData.load(tmp_path / "builtin.npz")
    for name in ("template", "faces", "skin_weights", "expression_deltas", "larynx_maps", "shape_deltas", "faces_uv"):
        np.testing.assert_array_equal(getattr(loaded, name), getattr(builtin_rig.rig, name))
    assert list(loaded.joint_names) == builtin_rig.joint_names


def broken_copy(release, tmp_path, edit):
    copy = tmp_path / "copy"
    shutil.copytree(release, copy)
    edit(copy / "HACK-Model" / "model", copy / "ICT-FaceKit" / "FaceXModel")
    return copy


@pytest.mark.parametrize("edit, message", [
    (lambda m, i: (m / "bones_neutral.json").unlink(), r"bones_neutral\.json: missing"),
    (lambda m, i: (m / "bones_neutral.json").write_text("{not json"), r"bones_neutral\.json: malformed JSON"),
    (lambda m, i: (m / "bones_neutral.json").write_text(json.dumps({"c7t1": {}})),
     r"bones_neutral\.json: bones \['c7t1'\], expected"),
    (lambda m, i: np.save(m / "weight_map_smooth.npy", np.ones((7, 3))),
     r"weight_map_smooth\.npy: shape \(7, 3\), expected \[8,"),
    (lambda m, i: (m / "Lc_mid.png").write_bytes(b"not a png"), r"Lc_mid\.png: not a readable image"),
    (lambda m, i: (m / "ts_larynx.npy").unlink(), r"ts_larynx\.npy: missing"),
    (lambda m, i: (i / "jawOpen.obj").unlink(), r"jawOpen\.obj: missing \(ICT-FaceKit expression 'jawOpen'\)"),
    (lambda m, i: (m / "000_generic_neutral_mesh_newuv.obj").write_text("v 0 0 0\nf 1 2 3\n"),
     r"000_generic_neutral_mesh_newuv\.obj: 'f' record 1 references vertex 2, but the file has 1"),
])
def test_bad_asset_folders_name_the_file(release, tmp_path, edit, message):
    broken = broken_copy(release, tmp_path, edit)
    with pytest.raises(InputError, match=message):
        convert(broken / "HACK-Model", broken / "ICT-FaceKit")


def test_bad_rig_files_are_explained(tmp_path):
    with pytest.raises(InputError, match="rig file not found"):
        HeadNeckModel.load(tmp_path / "none.npz")
    (tmp_path / "junk.npz").write_bytes(b"junk")
    with pytest.raises(InputError, match="junk.npz: not a rig file"):
        HeadNeckModel.load(tmp_path / "junk.npz")
    with pytest.raises(InputError, match="is a folder; convert the release first"):
        HeadNeckModel.load(tmp_path)


@pytest.mark.parametrize("keep", [0.5, 0.98])
def test_truncated_rig_file_is_named(builtin_rig, tmp_path, keep):
    """A copy cut short (an interrupted download): the zip directory or an archive member is missing."""
    builtin_rig.rig.save(tmp_path / "whole.npz")
    data = (tmp_path / "whole.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(data[:int(len(data) * keep)])
    with pytest.raises(InputError, match=r"cut\.npz: not a rig file, or a damaged one"):
        RigData.load(tmp_path / "cut.npz")


def test_obj_round_trip(builtin_rig, tmp_path):
    vertices = builtin_rig(torch.full((1, 8, 3), 0.05))[0].numpy()
    write_obj(tmp_path / "posed.obj", vertices, builtin_rig.faces.numpy(), builtin_rig.rig.uv_coords,
              builtin_rig.rig.faces_uv)
    mesh = read_obj(tmp_path / "posed.obj")
    assert np.abs(mesh.vertices - vertices).max() < 2e-6
    np.testing.assert_array_equal(mesh.faces, builtin_rig.faces.numpy())
    np.testing.assert_array_equal(mesh.faces_uv, builtin_rig.rig.faces_uv)
    assert not list(tmp_path.glob(".*tmp*"))  # no temporary left behind


def test_ply_is_valid_binary(builtin_rig, tmp_path):
    vertices = builtin_rig.template.numpy()
    faces = builtin_rig.faces.numpy()
    write_ply(tmp_path / "frame.ply", vertices, faces)
    data = (tmp_path / "frame.ply").read_bytes()
    header, body = data.split(b"end_header\n", 1)
    assert f"element vertex {len(vertices)}".encode() in header and f"element face {len(faces)}".encode() in header
    read_vertices = np.frombuffer(body[: len(vertices) * 12], dtype="<f4").reshape(-1, 3)
    records = np.frombuffer(body[len(vertices) * 12:], dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    np.testing.assert_array_equal(read_vertices, vertices.astype("<f4"))
    assert (records["n"] == 3).all()
    np.testing.assert_array_equal(records["idx"], faces)


def test_triangulate_fans_quads():
    quads = np.array([[0, 1, 2, 3], [4, 5, 6, 7]])
    np.testing.assert_array_equal(triangulate(quads), [[0, 1, 2], [4, 5, 6], [0, 2, 3], [4, 6, 7]])


def test_assets_command_converts_and_reports(release, builtin_rig, tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parents[1]
    out = tmp_path / "rig.npz"
    command = [sys.executable, "-m", "data.assets", f"hack_dir={release / 'HACK-Model'}",
               f"ict_dir={release / 'ICT-FaceKit'}", f"out={out}"]
    result = subprocess.run(command, cwd=repo, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert f"{builtin_rig.num_vertices} vertices" in result.stdout and "8 joints, 55 expressions" in result.stdout
    assert HeadNeckModel.load(out).num_vertices == builtin_rig.num_vertices
    missing = subprocess.run([sys.executable, "-m", "data.assets", f"out={out}"], cwd=repo, capture_output=True,
                             text=True, timeout=300)
    assert missing.returncode == 2 and missing.stderr.strip() == (
        "error: missing hack_dir=..., ict_dir=... (see configs/assets.yaml)")
    wrong = subprocess.run(command[:3] + [f"ict_dir={tmp_path / 'nowhere'}", "out_file=x"], cwd=repo,
                           capture_output=True, text=True, timeout=300)
    assert wrong.returncode == 2 and "Key 'out_file' not in 'AssetsCli'" in wrong.stderr
