"""USD export (scene.usd): USD's own skinning (``UsdSkel.BakeSkinning``) against the rig, USD's own validators,
the stage's layout read back with pxr, usdz/usda and metres, the giraffe, pose correctives, bad input, and
Blender's USD importer as an independent consumer (where a Python with the ``bpy`` wheel is found).
"""
from __future__ import annotations

import dataclasses
import importlib.util
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import numpy as np
import pytest

from base.cli import compose_config, run_cli
from base.errors import InputError
from data.params import save_params
from scene.gltf import rig_vertices
from scene.gltf.cli import run as gltf_run
from scene.usd import UsdMissing, baked_points, export_usd, time_codes, validation_errors
from tests.conftest import requires_shared
from tests.test_gltf import clip, corrective_rig  # noqa: F401  (a fixture)

TOLERANCE_CM = 0.01            # the bound for USD's skinning of the file against the rig
READER = Path(__file__).with_name("blender_usd_reader.py")


def usd_clip(rig, frames: int = 30, seed: int = 0):
    """tests.test_gltf's clip with weights outside [0, 1]: jawOpen from -0.3 to 1.4, a larynx up to 1.3
    times the generic one (the larynx targets' weights eta * hat exceed 1 before scene.usd rescales them)."""
    params = clip(rig, frames=frames, seed=seed)
    psi = params.psi.copy()
    psi[:, rig.expression_names.index("jawOpen")] = np.linspace(-0.3, 1.4, frames)
    eta = 1.0 + 0.3 * np.sin(np.linspace(0, 2 * np.pi, frames))
    return dataclasses.replace(params, psi=psi, eta=eta)


def baked_error_cm(path: Path, rig, params, frames=None, scale: float = 1.0) -> np.ndarray:
    """Per frame, the largest distance (cm) between USD's skinning of ``path`` and the rig."""
    frames = np.arange(len(params)) if frames is None else np.asarray(frames)
    ours = baked_points(path, time_codes(params)[frames]) * scale
    return np.linalg.norm(ours - rig_vertices(rig, params, frames), axis=-1).max(axis=1)


@pytest.fixture(scope="module")
def builtin_usd(builtin_rig, tmp_path_factory):
    params = usd_clip(builtin_rig)
    path = tmp_path_factory.mktemp("usd") / "anim.usdc"
    report = export_usd(params, builtin_rig, path, check=True)
    return params, path, report


def test_usd_skinning_reproduces_the_builtin_rig(builtin_rig, builtin_usd):
    params, path, report = builtin_usd
    errors = baked_error_cm(path, builtin_rig, params)
    assert len(errors) == 30 and errors.max() < TOLERANCE_CM, errors
    assert report.max_error_cm < TOLERANCE_CM and report.larynx_error_cm < 0.005


def test_stage_layout(builtin_rig, builtin_usd):
    from pxr import Usd, UsdGeom, UsdSkel

    params, path, report = builtin_usd
    stage = Usd.Stage.Open(str(path))
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.y
    assert stage.GetTimeCodesPerSecond() == 30.0 and stage.GetFramesPerSecond() == 30.0
    assert (stage.GetStartTimeCode(), stage.GetEndTimeCode()) == pytest.approx((0.0, 29.0))
    skeleton = UsdSkel.Skeleton(stage.GetPrimAtPath("/hackneck/Skeleton"))
    joints = list(skeleton.GetJointsAttr().Get())
    assert joints[0] == "c7t1" and joints[-1] == "c7t1/c6c7/c5c6/c4c5/c3c4/c2c3/c1c2/oc1"
    # the bind transforms put the joints where the rig's rest pose has them (cm; USD's row-vector matrices)
    bind = np.array([np.array(m) for m in skeleton.GetBindTransformsAttr().Get()])
    rest = builtin_rig.rig.joint_rest_local.astype(np.float64)
    world = [rest[0]]
    for j in range(1, len(rest)):
        world.append(world[j - 1] @ rest[j])
    np.testing.assert_allclose(bind[:, 3, :3], np.array(world)[:, :3, 3], atol=1e-4)

    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/hackneck/head_neck"))
    assert len(mesh.GetPointsAttr().Get()) == builtin_rig.num_vertices
    assert len(mesh.GetFaceVertexCountsAttr().Get()) == len(builtin_rig.rig.faces)
    st = UsdGeom.PrimvarsAPI(mesh).GetPrimvar("st")
    assert st.GetInterpolation() == "faceVarying" and len(st.Get()) == len(builtin_rig.rig.uv_coords)
    binding = UsdSkel.BindingAPI(mesh)
    assert binding.GetJointIndicesPrimvar().GetElementSize() == 8
    assert binding.GetJointWeightsPrimvar().GetInterpolation() == "vertex"
    shapes = list(binding.GetBlendShapesAttr().Get())
    assert shapes[:2] == ["browDown_L", "browDown_R"] and all(s.startswith("larynx_tau_") for s in shapes[55:-2])
    assert len(shapes) == 55 + report.larynx_targets + 2 and shapes[-2:] == ["jawOpen_over", "jawOpen_under"]

    # every weight in [0, 1] (Blender clamps to it); jawOpen's -0.3 .. 1.4 split as jawOpen + 0.4 over - 0.3 under
    animation = UsdSkel.Animation(stage.GetPrimAtPath("/hackneck/Skeleton/Animation"))
    assert len(animation.GetRotationsAttr().GetTimeSamples()) == 30
    weights = np.array([np.array(animation.GetBlendShapeWeightsAttr().Get(t)) for t in range(30)])
    assert weights.min() >= 0 and weights.max() <= 1
    jaw = shapes.index("jawOpen")
    np.testing.assert_allclose(weights[:, jaw] + 0.4 * weights[:, -2] - 0.3 * weights[:, -1], params.psi[:, jaw],
                               atol=1e-6)

    def offsets(name):
        return np.array(UsdSkel.BlendShape(stage.GetPrimAtPath(f"/hackneck/head_neck/{name}")).GetOffsetsAttr().Get())
    np.testing.assert_allclose(offsets("jawOpen_over"), 0.4 * offsets("jawOpen"), atol=1e-6)
    np.testing.assert_allclose(offsets("jawOpen_under"), -0.3 * offsets("jawOpen"), atol=1e-6)
    larynx = weights[:, 55:-2]
    assert larynx.max() == pytest.approx(1.0)                         # rescaled by the largest weight...
    assert 1.2 < report.larynx_scale <= params.eta.max()              # ...eta * hat, eta up to 1.3
    assert stage.GetRootLayer().customLayerData["larynx_target_scale"] == pytest.approx(report.larynx_scale)


def test_validators(builtin_usd, tmp_path):
    from pxr import Sdf

    assert validation_errors(builtin_usd[1]) == []
    broken = Sdf.Layer.OpenAsAnonymous(str(builtin_usd[1]))
    broken.ClearDefaultPrim()
    broken.pseudoRoot.ClearInfo("metersPerUnit")
    broken.GetPrimAtPath("/hackneck/head_neck").SetInfo("apiSchemas", Sdf.TokenListOp.Create(
        prependedItems=["MaterialBindingAPI"]))           # SkelBindingAPI gone
    broken.Export(str(tmp_path / "broken.usda"))
    found = " ".join(validation_errors(tmp_path / "broken.usda"))
    for name in ("SkelBindingApiAppliedValidator", "defaultPrim", "metersPerUnit"):
        assert name in found, found


def test_usdz_in_metres_opens_in_a_fresh_process(builtin_rig, tmp_path):
    params = usd_clip(builtin_rig, frames=8, seed=1)
    path = tmp_path / "anim.usdz"
    export_usd(params, builtin_rig, path, units="m", morph_normals=False)
    assert validation_errors(path) == []           # the usdz package validators included
    with zipfile.ZipFile(path) as package:
        assert [i.filename for i in package.infolist()] == ["anim.usdc"]
        assert all(i.compress_type == zipfile.ZIP_STORED for i in package.infolist())
    assert baked_error_cm(path, builtin_rig, params, [0, 4, 7], scale=100.0).max() < TOLERANCE_CM
    script = ("import sys; from pxr import Usd, UsdGeom; s = Usd.Stage.Open(sys.argv[1]); "
              "print(UsdGeom.GetStageMetersPerUnit(s), len(s.GetPrimAtPath('/hackneck/head_neck')"
              ".GetAttribute('points').Get()), s.GetEndTimeCode())")
    out = subprocess.run([sys.executable, "-c", script, str(path)], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["1.0", str(builtin_rig.num_vertices), "7.0"]


def test_command_line_picks_usd_by_suffix(builtin_rig, tmp_path, capsys):
    params = usd_clip(builtin_rig, frames=4, seed=2)
    save_params(tmp_path / "params.npz", params)
    run_cli("gltf", gltf_run, [f"source={tmp_path / 'params.npz'}", f"out={tmp_path / 'anim.usda'}", "check=false",
                               "morph_normals=false", "usd_units=m"])
    assert "USD (usda, UsdSkel)" in capsys.readouterr().out
    text = (tmp_path / "anim.usda").read_text()
    assert text.startswith("#usda 1.0\n") and "metersPerUnit = 1" in text and 'upAxis = "Y"' in text


def test_pose_correctives(corrective_rig, tmp_path):  # noqa: F811
    params = usd_clip(corrective_rig, frames=6, seed=3)
    report = export_usd(params, corrective_rig, tmp_path / "c.usdc", morph_normals=False)
    assert report.corrective_targets == 7 * 9
    assert baked_error_cm(tmp_path / "c.usdc", corrective_rig, params).max() < TOLERANCE_CM


def test_bad_input(builtin_rig, turned_rig, tmp_path, monkeypatch, capsys):
    params = usd_clip(builtin_rig, frames=4)
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match=r"file/x\.usdc: cannot write there"):
        export_usd(params, builtin_rig, tmp_path / "file" / "x.usdc")
    with pytest.raises(InputError, match="checksum"):
        export_usd(params, turned_rig, tmp_path / "x.usdc")
    with pytest.raises(InputError, match=r"x\.obj: a USD file ends in \.usdc, \.usda, \.usdz, \.usd"):
        export_usd(params, builtin_rig, tmp_path / "x.obj")
    save_params(tmp_path / "params.npz", params)
    monkeypatch.setitem(sys.modules, "pxr.UsdSkel", None)      # as if usd-core were not installed
    with pytest.raises(UsdMissing, match="pip install usd-core"):
        export_usd(params, builtin_rig, tmp_path / "x.usdc")
    with pytest.raises(SystemExit) as exit_:
        run_cli("gltf", gltf_run, [f"source={tmp_path / 'params.npz'}", f"out={tmp_path / 'x.usdz'}"])
    assert exit_.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "usd-core" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "params.npz"]   # nothing else written


def test_infer_and_retarget_onto_the_giraffe_export_usd(tmp_path):
    from base.files import write_csv
    from infer import run as infer_run
    from models.rig import HeadNeckModel
    from motion.retarget import run as retarget_run

    frames = 10
    time = np.arange(frames) / 30.0
    write_csv(tmp_path / "take.csv", {"time": time, "jawOpen": 0.3 + 0.2 * np.sin(5 * time),
                                      "HeadYaw": 0.3 * np.sin(time), "HeadPitch": np.full(frames, 0.1),
                                      "HeadRoll": np.zeros(frames)}, float_format="%.9g")
    out = tmp_path / "infer"
    infer_run(compose_config("infer", [f"expressions={tmp_path / 'take.csv'}", f"out_dir={out}", "checkpoint=none",
                                       "head2neck=none", "plot=false", "allow_missing=true", "export=[usd]",
                                       "usd_format=usdz"]))
    assert validation_errors(out / "anim.usdz") == []
    # the giraffe (retargeted, its rig saved as character.npz) exports as any rig does
    giraffe = tmp_path / "giraffe"
    run_cli("retarget", retarget_run, argv=[f"source={out / 'params.npz'}", "character=giraffe",
                                            f"out_dir={giraffe}", "meshes=false", "export=[usd]"])
    assert validation_errors(giraffe / "animation.usdc") == []
    from data.params import load_params

    rig = HeadNeckModel.load(giraffe / "character.npz")
    assert baked_error_cm(giraffe / "animation.usdc", rig, load_params(giraffe / "params.npz")).max() < TOLERANCE_CM


@requires_shared
@pytest.mark.shared
def test_usd_skinning_reproduces_the_real_rig(real_rig, tmp_path):
    params = usd_clip(real_rig, frames=12, seed=4)
    path = tmp_path / "real.usdc"
    export_usd(params, real_rig, path, morph_normals=False)
    assert validation_errors(path) == []
    assert baked_error_cm(path, real_rig, params).max() < TOLERANCE_CM


# ----------------------------------------------------------------------------- Blender's USD importer


def bpy_python() -> str | None:
    """A Python whose ``import bpy`` works: $HACKNECK_BPY_PYTHON, else this one if it has bpy."""
    given = os.environ.get("HACKNECK_BPY_PYTHON")
    if given:
        return given if shutil.which(given) or Path(given).is_file() else None
    return sys.executable if importlib.util.find_spec("bpy") is not None else None


@pytest.mark.skipif(bpy_python() is None, reason="no Python with the bpy wheel (pip install bpy, Python 3.11, "
                    "numpy<2: a separate environment; HACKNECK_BPY_PYTHON=<its python>)")
def test_blender_imports_the_file(builtin_rig, builtin_usd, tmp_path):
    """Blender frame f is time code f (the clip's frame f); its shape keys keep their [0, 1] sliders, which
    the file's weights respect: jawOpen -0.12 (frame 2, through jawOpen_under), 0.52 and 1.28 (frame 27,
    through jawOpen_over), the larynx up to 1.3 times the generic one."""
    params, path, _ = builtin_usd
    frames = [2, 14, 27]
    subprocess.run([bpy_python(), str(READER), str(path), str(tmp_path / "b.npz"), *map(str, frames)], check=True,
                   capture_output=True, timeout=300)
    blender = np.load(tmp_path / "b.npz")
    assert (int(blender["frame_start"]), int(blender["frame_end"])) == (0, 29)
    errors = np.linalg.norm(blender["vertices"] - rig_vertices(builtin_rig, params, frames), axis=-1).max(axis=1)
    assert errors.max() < TOLERANCE_CM, errors
