"""FBX export (scene.fbx) through headless Blender: Blender's own re-import evaluated at every frame of a
300-frame clip against the rig, an independent reader (ufbx) for the file's structure, units and take,
and the one-line refusal when Blender is absent.  Skips with the reason where Blender or ufbx is missing
(``.ci/run`` installs Blender with apt-get)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from data.params import save_params
from scene.fbx import export_fbx
from scene.gltf import METRES_PER_CM, export_glb, rig_vertices
from scene.gltf.mesh import split_uv_seams
from tests.blender_sampling import blender_vertices
from tests.test_gltf import clip

REPO = Path(__file__).resolve().parents[1]
TOLERANCE_CM = 0.01            # the bound for the FBX re-imported by Blender
FRAMES = 300


def blender_ready() -> str | None:
    """Why the Blender tests cannot run here, or None."""
    from scene.fbx import BlenderMissing, blender_executable

    try:
        blender_executable()
    except BlenderMissing as e:
        return str(e)
    return None


needs_blender = pytest.mark.skipif(blender_ready() is not None, reason=str(blender_ready()))


@pytest.fixture(scope="module")
def fbx_clip(builtin_rig, tmp_path_factory):
    """A 300-frame clip at 30 fps on the built-in rig and its FBX (units cm) written once."""
    if blender_ready() is not None:
        pytest.skip(blender_ready())
    folder = tmp_path_factory.mktemp("fbx")
    params = clip(builtin_rig, frames=FRAMES, amplitude=0.12, tau_amplitude=0.03)
    report = export_fbx(params, builtin_rig, folder / "clip.fbx", units="cm", take="clip")
    return params, report.path


def gltf_vertex_order(rig) -> np.ndarray:
    """The rig vertex of each GLB (and so Blender) vertex: the GLB splits vertices at UV seams."""
    return split_uv_seams(rig).rig_index


def to_blender_world(gltf_metres: np.ndarray) -> np.ndarray:
    """glTF / rig axes (y up) -> Blender's world (z up): Blender (x, y, z) = glTF (x, -z, y)."""
    return np.stack([gltf_metres[..., 0], -gltf_metres[..., 2], gltf_metres[..., 1]], axis=-1)


@needs_blender
def test_blender_reimports_the_fbx_within_a_hundredth_of_a_millimetre_at_every_frame(builtin_rig, fbx_clip):
    params, path = fbx_clip
    frames = np.arange(FRAMES)
    got = blender_vertices(path, params.fps, frames)
    expected = to_blender_world(rig_vertices(builtin_rig, params, frames)[:, gltf_vertex_order(builtin_rig)]
                                * METRES_PER_CM)
    assert got["vertices"].shape == expected.shape
    error_cm = np.linalg.norm(got["vertices"] - expected, axis=-1) / METRES_PER_CM
    moved_cm = np.linalg.norm(expected - expected[:1], axis=-1).max() / METRES_PER_CM
    assert moved_cm > 2.0, "the clip must move the mesh for the check to mean anything"
    assert error_cm.max() < TOLERANCE_CM, f"worst frame {error_cm.max(1).argmax()}: {error_cm.max():.4f} cm"
    assert list(got["bones"]) == list(builtin_rig.joint_names)
    assert set(builtin_rig.expression_names) <= set(got["shape_keys"])


def read_with_ufbx(path: Path) -> dict:
    """What ufbx (an FBX reader independent of Blender) finds in ``path``; skips without ufbx."""
    pytest.importorskip("ufbx", reason="ufbx (pip install ufbx) reads FBX independently of Blender")
    result = subprocess.run([sys.executable, str(REPO / "tests" / "ufbx_reader.py"), str(path)],
                            capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr[-2000:]
    return json.loads(result.stdout)


@needs_blender
def test_an_independent_reader_finds_the_skin_the_channels_the_units_and_the_take(builtin_rig, fbx_clip):
    params, path = fbx_clip
    found = read_with_ufbx(path)
    assert found["unit_meters"] == pytest.approx(0.01)          # centimetres
    assert found["axes"] == ["POSITIVE_X", "POSITIVE_Y", "POSITIVE_Z"]     # y up, the face towards +z
    assert found["fps"] == pytest.approx(params.fps)
    assert sorted(found["clusters"]) == sorted(builtin_rig.joint_names)
    assert found["mesh_visible"] == [True]
    assert set(builtin_rig.expression_names) <= set(found["channels"])
    assert sum(name.startswith("larynx_tau") for name in found["channels"]) >= 2
    assert len(found["stacks"]) == 1, f"one take holding skeleton and shape keys, got {found['stacks']}"
    name, begin, end = found["stacks"][0]
    assert name == "clip"
    assert begin == pytest.approx(0.0, abs=1e-9)
    assert end == pytest.approx((FRAMES - 1) / params.fps, abs=1e-6)
    # The rest mesh is stored in centimetres, in Blender's z-up axes under the file's y-up axis setting.
    assert found["extent"] == pytest.approx(np.ptp(builtin_rig.rig.template, axis=0)[[0, 2, 1]], rel=1e-4)


@needs_blender
def test_metre_units_store_metres_and_reimport_the_same_mesh(builtin_rig, tmp_path):
    short = clip(builtin_rig, frames=20, amplitude=0.12, seed=3)
    glb = tmp_path / "short.glb"
    export_glb(short, builtin_rig, glb, check=False)
    path = export_fbx(short, builtin_rig, tmp_path / "short.fbx", units="m", glb=glb).path
    found = read_with_ufbx(path)
    assert found["unit_meters"] == pytest.approx(1.0)
    assert found["extent"] == pytest.approx(np.ptp(builtin_rig.rig.template, axis=0)[[0, 2, 1]] * METRES_PER_CM,
                                            rel=1e-4)
    frames = [0, 7, 19]
    got = blender_vertices(path, short.fps, frames)["vertices"]
    expected = to_blender_world(rig_vertices(builtin_rig, short, frames)[:, gltf_vertex_order(builtin_rig)]
                                * METRES_PER_CM)
    assert np.abs(got - expected).max() / METRES_PER_CM < TOLERANCE_CM


@needs_blender
def test_infer_writes_anim_fbx_beside_the_glb(tmp_path):
    out = tmp_path / "run"
    result = subprocess.run([sys.executable, "infer.py", f"out_dir={out}", "export=[glb,fbx]", "plot=false",
                             "fbx_units=cm"], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-2000:]
    assert (out / "anim.fbx").stat().st_size > 100_000
    assert "FBX, one take of 360 frames at 30 fps, units cm" in result.stdout


def without_blender_env(tmp_path: Path) -> dict:
    """An environment whose PATH has no Blender (only an empty folder) and no $BLENDER."""
    empty = tmp_path / "bin"
    empty.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "BLENDER"}
    env["PATH"] = str(empty)
    return env


@pytest.mark.parametrize("command", [
    ["infer.py", "export=[fbx]", "plot=false"],
    ["-m", "motion.retarget", "export=[fbx]"],
    ["-m", "scene.gltf", "out={out}/anim.fbx"],
])
def test_without_blender_each_tool_says_how_to_install_it_and_writes_nothing(tmp_path, builtin_rig, command):
    params_file = tmp_path / "params.npz"
    save_params(params_file, clip(builtin_rig, frames=4))
    out = tmp_path / "out"
    args = [a.format(out=out) for a in command]
    args += {"infer.py": [f"out_dir={out}"], "-m": []}[args[0]]
    if "motion.retarget" in args:
        args += [f"source={params_file}", f"out_dir={out}"]
    if "scene.gltf" in args:
        args += [f"source={params_file}"]
    result = subprocess.run([sys.executable, *args], cwd=REPO, capture_output=True, text=True, timeout=300,
                            env=without_blender_env(tmp_path))
    assert result.returncode == 2, result.stderr[-2000:]
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and "needs Blender" in lines[0] and "apt-get install blender" in lines[0], lines
    assert not out.exists() or not any(out.iterdir())


def test_fbx_units_are_checked_before_anything_runs(builtin_rig, tmp_path):
    with pytest.raises(ValueError, match="fbx_units=mm: expected one of cm, m"):
        export_fbx(clip(builtin_rig, frames=2), builtin_rig, tmp_path / "x.fbx", units="mm")
    assert not (tmp_path / "x.fbx").exists()

