"""GLB export (scene.gltf): the Khronos validator, and an independent re-import that evaluates the file.

The evaluator below reads the GLB's bytes itself (header, JSON and BIN chunks, accessors with sparse
storage, node transforms, skin, morph targets, animation samplers) without pygltflib or the exporter's
arrays, and poses the mesh at frame times as a glTF viewer would (glTF 2.0 specification, sections 3.7
"Skins", 3.8 "Morph targets", 3.11 "Animations"); its vertices, mapped back to the rig through
``mesh.extras.rig_vertex_index``, must match ``rig(theta, psi, tau, eta)`` within 0.05 cm (the issue's
bound).  The validator runs where Node.js and npm are present (installed once into a cache folder
outside the repository); the test says so when it skips.
"""
from __future__ import annotations

import dataclasses
import json
import os
import shutil
import struct
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from base.cli import run_cli
from base.errors import InputError
from data.mesh_io import triangulate
from data.params import AnimationParams, rig_checksum, save_params
from models.rig import HeadNeckModel
from scene.gltf import build_glb, export_glb, larynx_targets, resolve_rig
from scene.gltf.cli import run

REPO = Path(__file__).resolve().parents[1]
VALIDATOR_SCRIPT = REPO / "tests" / "gltf_validate.mjs"
VALIDATOR_PREFIX = Path(os.environ.get("GLTF_VALIDATOR_PREFIX",
                                       Path.home() / ".cache" / "hackneck" / "gltf-validator"))
TOLERANCE_CM = 0.05              # the bound for the re-imported mesh
# The HACK release's template: 14,269 vertex/UV pairs for 14,062 vertices (the issue, counted in the OBJ).
HACK_UV_PAIRS, HACK_VERTICES = 14269, 14062


# ----------------------------------------------------------------------------- clips


def clip(rig: HeadNeckModel, frames: int = 12, fps: float = 30.0, amplitude: float = 0.08, tau_amplitude: float = 0.025,
         seed: int = 0, start: float = 0.0) -> AnimationParams:
    """A clip with nods, turns and tilts at every joint (anatomical frames), sparse expressions, a sliding
    larynx and a varying larynx size."""
    rng = np.random.default_rng(seed)
    t = start + np.arange(frames) / fps
    phase = np.linspace(0, 2 * np.pi, frames)
    anatomical = np.zeros((frames, rig.num_joints, 3))
    anatomical[..., 0] = amplitude * np.sin(phase)[:, None]
    anatomical[..., 1] = 0.8 * amplitude * np.sin(2 * phase + 0.4)[:, None]
    anatomical[..., 2] = 0.5 * amplitude * np.cos(phase)[:, None]
    theta = rig.from_anatomical(torch.tensor(anatomical, dtype=torch.float32))
    psi = rng.uniform(0, 0.8, (frames, len(rig.expression_names))) * (rng.uniform(size=len(rig.expression_names)) < 0.4)
    tau = tau_amplitude * np.sin(1.5 * phase)
    eta = 1.0 + 0.2 * np.sin(phase)
    with torch.no_grad():
        head = rig.head_rotation(theta)
    return AnimationParams(time=t, fps=fps, psi=psi, tau=tau, eta=eta, theta=theta.numpy(), head_rotation=head.numpy(),
                           joint_names=rig.joint_names, expression_names=rig.expression_names,
                           rig_checksum=rig_checksum(rig.rig))


def rig_mesh(rig: HeadNeckModel, params: AnimationParams, frames) -> np.ndarray:
    with torch.no_grad():
        return rig(torch.as_tensor(params.theta[frames]), torch.as_tensor(params.psi[frames]),
                   torch.as_tensor(params.tau[frames]), torch.as_tensor(params.eta[frames])).double().numpy()


@pytest.fixture(scope="module")
def corrective_rig(builtin_rig):
    """The built-in rig with random pose correctives on every non-root (R - I) feature (the built-in and
    public HACK rigs have none): ~0.5 cm per unit feature at the neck."""
    data = builtin_rig.rig
    rng = np.random.default_rng(3)
    n = len(data.template)
    near_neck = np.exp(-(((data.template[:, 1] + 5) / 6) ** 2))[None, :, None]
    basis = rng.normal(0, 0.5, (len(data.joint_names) * 9, n, 3)) * near_neck
    return HeadNeckModel(dataclasses.replace(data, pose_correctives=basis.reshape(-1, n * 3).astype(np.float32)))


# ----------------------------------------------------------------------------- an independent GLB reader

COMPONENTS = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32, 5126: np.float32}
WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT4": 16}


class Glb:
    """A GLB file read with struct and numpy: ``doc`` the JSON, ``accessor(i)`` the data [count, width]."""

    def __init__(self, path: Path):
        raw = path.read_bytes()
        magic, version, length = struct.unpack_from("<4sII", raw, 0)
        assert magic == b"glTF" and version == 2 and length == len(raw)
        json_length, json_type = struct.unpack_from("<II", raw, 12)
        assert json_type == 0x4E4F534A
        self.doc = json.loads(raw[20:20 + json_length])
        offset = 20 + json_length
        bin_length, bin_type = struct.unpack_from("<II", raw, offset)
        assert bin_type == 0x004E4942
        self.bin = raw[offset + 8: offset + 8 + bin_length]

    def view(self, index: int, dtype, count: int, width: int, offset: int = 0) -> np.ndarray:
        view = self.doc["bufferViews"][index]
        stride = view.get("byteStride", np.dtype(dtype).itemsize * width)
        start = view.get("byteOffset", 0) + offset
        rows = [np.frombuffer(self.bin, dtype, width, start + i * stride) for i in range(count)] \
            if stride != np.dtype(dtype).itemsize * width else \
            [np.frombuffer(self.bin, dtype, count * width, start).reshape(count, width)]
        return np.concatenate(rows).reshape(count, width)

    def accessor(self, index: int) -> np.ndarray:
        acc = self.doc["accessors"][index]
        dtype, width = COMPONENTS[acc["componentType"]], WIDTH[acc["type"]]
        if "bufferView" in acc:
            out = self.view(acc["bufferView"], dtype, acc["count"], width, acc.get("byteOffset", 0)).copy()
        else:
            out = np.zeros((acc["count"], width), dtype)
        if "sparse" in acc:
            sparse = acc["sparse"]
            rows = self.view(sparse["indices"]["bufferView"], COMPONENTS[sparse["indices"]["componentType"]],
                             sparse["count"], 1, sparse["indices"].get("byteOffset", 0))[:, 0]
            out[rows] = self.view(sparse["values"]["bufferView"], dtype, sparse["count"], width,
                                  sparse["values"].get("byteOffset", 0))
        return out


def quaternion_matrix(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def slerp(a: np.ndarray, b: np.ndarray, s: float) -> np.ndarray:
    dot = float(np.dot(a, b))
    if dot < 0:
        b, dot = -b, -dot
    if dot > 0.9995:
        q = a + s * (b - a)
        return q / np.linalg.norm(q)
    angle = np.arccos(dot)
    return (np.sin((1 - s) * angle) * a + np.sin(s * angle) * b) / np.sin(angle)


def sample(times: np.ndarray, values: np.ndarray, t: float, rotation: bool) -> np.ndarray:
    """A LINEAR glTF sampler at time t: keyframes [K], values [K, ...]."""
    if t <= times[0]:
        return values[0]
    if t >= times[-1]:
        return values[-1]
    k = int(np.searchsorted(times, t, side="right")) - 1
    s = (t - times[k]) / (times[k + 1] - times[k])
    return slerp(values[k], values[k + 1], s) if rotation else (1 - s) * values[k] + s * values[k + 1]


def evaluate(glb: Glb, t: float) -> np.ndarray:
    """The skinned, morphed positions [V,3] (metres) of the one mesh at animation time t."""
    doc = glb.doc
    primitive = doc["meshes"][0]["primitives"][0]
    mesh_node = next(i for i, n in enumerate(doc["nodes"]) if "mesh" in n)
    channels = {}
    animation = doc["animations"][0]
    for channel in animation["channels"]:
        sampler = animation["samplers"][channel["sampler"]]
        assert sampler.get("interpolation", "LINEAR") == "LINEAR"
        keys = glb.accessor(sampler["input"])[:, 0]
        out = glb.accessor(sampler["output"])
        target = channel["target"]
        if target["path"] == "weights":
            out = out.reshape(len(keys), -1)
        channels[(target["node"], target["path"])] = sample(keys, out, t, target["path"] == "rotation")

    weights = channels.get((mesh_node, "weights"), np.asarray(doc["meshes"][0].get("weights", [])))
    positions = glb.accessor(primitive["attributes"]["POSITION"]).astype(np.float64)
    for w, target in zip(weights, primitive.get("targets", [])):
        positions = positions + w * glb.accessor(target["POSITION"])

    parent = {c: i for i, n in enumerate(doc["nodes"]) for c in n.get("children", [])}

    def world(i: int) -> np.ndarray:
        node = doc["nodes"][i]
        local = np.eye(4)
        if "matrix" in node:
            local = np.array(node["matrix"]).reshape(4, 4).T
        else:
            rotation = channels.get((i, "rotation"), np.array(node.get("rotation", [0, 0, 0, 1.0])))
            scale = np.array(node.get("scale", [1, 1, 1.0]))
            local[:3, :3] = quaternion_matrix(np.asarray(rotation, np.float64)) * scale
            local[:3, 3] = channels.get((i, "translation"), node.get("translation", [0, 0, 0]))
        return local if i not in parent else world(parent[i]) @ local

    skin = doc["skins"][doc["nodes"][mesh_node]["skin"]]
    inverse_bind = glb.accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
    joint_matrices = np.stack([world(j) @ ibm for j, ibm in zip(skin["joints"], inverse_bind)])
    skinned = np.zeros_like(positions)
    homogeneous = np.concatenate([positions, np.ones((len(positions), 1))], axis=1)
    slot = 0
    while f"JOINTS_{slot}" in primitive["attributes"]:
        joints = glb.accessor(primitive["attributes"][f"JOINTS_{slot}"]).astype(np.int64)
        weights = glb.accessor(primitive["attributes"][f"WEIGHTS_{slot}"]).astype(np.float64)
        for k in range(4):
            skinned += weights[:, k, None] * np.einsum("vab,vb->va", joint_matrices[joints[:, k], :3], homogeneous)
        slot += 1
    return skinned


def reimport_error_cm(path: Path, rig: HeadNeckModel, params: AnimationParams, frames) -> float:
    glb = Glb(path)
    index = np.asarray(glb.doc["meshes"][0]["extras"]["rig_vertex_index"])
    expected = rig_mesh(rig, params, frames)
    worst = 0.0
    for frame, target in zip(frames, expected):
        ours = evaluate(glb, float(np.float32(params.time[frame]))) * 100.0
        worst = max(worst, float(np.linalg.norm(ours - target[index], axis=1).max()))
    return worst


# ----------------------------------------------------------------------------- the validator


@pytest.fixture(scope="session")
def validator():
    """A function running the Khronos validator on GLB files -> one report dict per file; skips when
    Node.js or npm is absent or the package cannot be installed."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("Node.js/npm not found: the Khronos glTF validator check (npm gltf-validator) needs them")
    if not (VALIDATOR_PREFIX / "node_modules" / "gltf-validator").is_dir():
        VALIDATOR_PREFIX.mkdir(parents=True, exist_ok=True)
        try:
            done = subprocess.run([npm, "install", "--no-save", "--prefix", str(VALIDATOR_PREFIX), "gltf-validator"],
                                  capture_output=True, text=True, timeout=300)
        except subprocess.TimeoutExpired:
            pytest.skip("npm install gltf-validator timed out (offline?)")
        if done.returncode != 0:
            pytest.skip(f"npm install gltf-validator failed (offline?): {done.stderr.strip().splitlines()[-1:]}")

    def run(*paths: Path) -> list[dict]:
        done = subprocess.run([node, str(VALIDATOR_SCRIPT), "--prefix", str(VALIDATOR_PREFIX), *map(str, paths)],
                              capture_output=True, text=True, timeout=300)
        assert done.returncode in (0, 1), done.stderr
        return [json.loads(line) for line in done.stdout.splitlines()]

    return run


# ----------------------------------------------------------------------------- tests


@pytest.fixture(scope="module")
def builtin_export(builtin_rig, tmp_path_factory):
    params = clip(builtin_rig, frames=12)
    path = tmp_path_factory.mktemp("glb") / "builtin.glb"
    return path, params, export_glb(params, builtin_rig, path)


def test_validator_reports_no_errors(validator, builtin_rig, corrective_rig, builtin_export, tmp_path):
    four = tmp_path / "four.glb"
    export_glb(clip(builtin_rig), builtin_rig, four, max_influences=4, check=False)
    correctives = tmp_path / "correctives.glb"
    export_glb(clip(corrective_rig), corrective_rig, correctives, check=False)
    single = tmp_path / "single.glb"
    export_glb(clip(builtin_rig, frames=1), builtin_rig, single, check=False)
    reports = validator(builtin_export[0], four, correctives, single)
    assert [r["errors"] for r in reports] == [0, 0, 0, 0], [r["messages"] for r in reports]
    assert [r["warnings"] for r in reports] == [0, 0, 0, 0], [r["messages"] for r in reports]


def test_validator_catches_a_broken_file(validator, builtin_export, tmp_path):
    """The validator check can fail: weights no longer summing to 1 are an error."""
    glb = Glb(builtin_export[0])
    accessor = glb.doc["accessors"][glb.doc["meshes"][0]["primitives"][0]["attributes"]["WEIGHTS_0"]]
    view = glb.doc["bufferViews"][accessor["bufferView"]]
    raw = bytearray(builtin_export[0].read_bytes())
    start = 20 + struct.unpack_from("<I", raw, 12)[0] + 8 + view.get("byteOffset", 0)
    struct.pack_into("<f", raw, start, 0.5)        # vertex 0's first weight
    broken = tmp_path / "broken.glb"
    broken.write_bytes(bytes(raw))
    report = validator(broken)[0]
    assert report["errors"] >= 1
    assert any(m["code"] == "ACCESSOR_WEIGHTS_NON_NORMALIZED" for m in report["messages"])


def test_reimport_reproduces_the_builtin_rig(builtin_rig, builtin_export):
    path, params, report = builtin_export
    error = reimport_error_cm(path, builtin_rig, params, [0, 3, 7, 11])
    assert error < TOLERANCE_CM
    assert report.max_error_cm < TOLERANCE_CM
    # Not trivially small: the clip moves the mesh by centimetres.
    moved = np.linalg.norm(rig_mesh(builtin_rig, params, [3]) - rig_mesh(builtin_rig, params, [0]), axis=-1).max()
    assert moved > 1.0


def test_reimport_reproduces_pose_correctives(corrective_rig, tmp_path):
    params = clip(corrective_rig, frames=8, amplitude=0.15)
    report = export_glb(params, corrective_rig, tmp_path / "c.glb")
    assert report.corrective_targets == (corrective_rig.num_joints - 1) * 9
    assert reimport_error_cm(tmp_path / "c.glb", corrective_rig, params, [0, 2, 5, 7]) < TOLERANCE_CM
    # The correctives matter here: without them the mesh is off by more than the tolerance.
    plain = HeadNeckModel(dataclasses.replace(corrective_rig.rig, pose_correctives=np.zeros((0, 0), np.float32)))
    gap = np.linalg.norm(rig_mesh(plain, params, [2]) - rig_mesh(corrective_rig, params, [2]), axis=-1).max()
    assert gap > 10 * TOLERANCE_CM


def test_file_structure(builtin_rig, builtin_export):
    path, params, report = builtin_export
    glb = Glb(path)
    doc = glb.doc
    mesh = doc["meshes"][0]
    names = mesh["extras"]["targetNames"]
    assert names[:55] == list(builtin_rig.expression_names)
    assert len(names) == len(mesh["primitives"][0]["targets"]) == 55 + report.larynx_targets
    # times: from 0 and strictly increasing, at the clip's frames
    animation = doc["animations"][0]
    times = glb.accessor(animation["samplers"][0]["input"])[:, 0]
    assert times[0] == 0.0 and (np.diff(times) > 0).all()
    np.testing.assert_allclose(times, params.time, atol=1e-6)
    # joints: one node per rig joint under a common root; quaternions of unit length
    skin = doc["skins"][0]
    assert [doc["nodes"][j]["name"] for j in skin["joints"]] == list(builtin_rig.joint_names)
    root = skin["skeleton"]
    assert skin["joints"][0] in doc["nodes"][root]["children"]
    rotations = [glb.accessor(s["output"]) for s, c in zip(animation["samplers"], animation["channels"])
                 if c["target"]["path"] == "rotation"]
    assert len(rotations) == 8
    np.testing.assert_allclose(np.linalg.norm(np.concatenate(rotations), axis=1), 1.0, atol=1e-6)
    # inverse bind matrices: last row exactly [0, 0, 0, 1]
    inverse_bind = glb.accessor(skin["inverseBindMatrices"]).reshape(-1, 4, 4).transpose(0, 2, 1)
    assert (inverse_bind[:, 3] == [0, 0, 0, 1]).all()
    # weights: 8 influences (the built-in rig has 7-8 per vertex), sum 1 in float32
    attributes = mesh["primitives"][0]["attributes"]
    weights = np.concatenate([glb.accessor(attributes["WEIGHTS_0"]), glb.accessor(attributes["WEIGHTS_1"])], axis=1)
    assert np.abs(weights.astype(np.float64).sum(1) - 1.0).max() < 1e-6
    # POSITION bounds are the float32 extremes
    positions = glb.accessor(attributes["POSITION"])
    accessor = doc["accessors"][attributes["POSITION"]]
    assert accessor["min"] == positions.min(0).tolist() and accessor["max"] == positions.max(0).tolist()


def test_metres_and_rest_pose(builtin_rig, builtin_export):
    """The base positions (rest pose, morph weights 0) are the template in metres."""
    glb = Glb(builtin_export[0])
    index = np.asarray(glb.doc["meshes"][0]["extras"]["rig_vertex_index"])
    positions = glb.accessor(glb.doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"])
    np.testing.assert_allclose(positions * 100.0, builtin_rig.rig.template[index], atol=1e-4)
    height_m = positions[:, 1].max() - positions[:, 1].min()
    assert 0.30 < height_m < 0.40     # the built-in head and neck is ~33.5 cm tall


def test_normals_and_their_morph_deltas(builtin_export):
    """NORMAL is the area-weighted normal of the file's own mesh (welded back through rig_vertex_index), and
    base normal + a target's NORMAL delta is the normal of the mesh with that target at weight 1."""
    glb = Glb(builtin_export[0])
    mesh = glb.doc["meshes"][0]
    primitive = mesh["primitives"][0]
    index = np.asarray(mesh["extras"]["rig_vertex_index"])
    triangles = index[glb.accessor(primitive["indices"]).reshape(-1, 3)]     # in rig vertices

    def normals(positions: np.ndarray) -> np.ndarray:
        welded = np.zeros((index.max() + 1, 3))
        welded[index] = positions
        corners = welded[triangles]
        cross = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
        out = np.zeros_like(welded)
        for k in range(3):
            np.add.at(out, triangles[:, k], cross)
        return (out / np.linalg.norm(out, axis=1, keepdims=True))[index]

    base = glb.accessor(primitive["attributes"]["POSITION"]).astype(np.float64)
    stored = glb.accessor(primitive["attributes"]["NORMAL"])
    np.testing.assert_allclose(stored, normals(base), atol=1e-5)
    k = mesh["extras"]["targetNames"].index("jawOpen")
    target = primitive["targets"][k]
    moved = normals(base + glb.accessor(target["POSITION"]))
    morphed = stored + glb.accessor(target["NORMAL"])
    np.testing.assert_allclose(morphed, moved, atol=1e-4)
    assert np.abs(moved - stored).max() > 0.1         # the jaw turns normals noticeably


def test_uv_seams_split_vertices(builtin_rig, builtin_export):
    """Each glTF triangle is a rig triangle (same winding up to rotation) with the rig's per-corner UVs, and
    no two glTF vertices share a (rig vertex, UV)."""

    glb = Glb(builtin_export[0])
    primitive = glb.doc["meshes"][0]["primitives"][0]
    index = np.asarray(glb.doc["meshes"][0]["extras"]["rig_vertex_index"])
    triangles = glb.accessor(primitive["indices"]).reshape(-1, 3)
    uv = glb.accessor(primitive["attributes"]["TEXCOORD_0"])
    data = builtin_rig.rig
    rig_triangles = triangulate(data.faces)
    rig_uv = data.uv_coords[triangulate(data.faces_uv)]                 # [F,3,2]
    assert len(triangles) == len(rig_triangles)
    corners = {tuple(sorted(t)): k for k, t in enumerate(rig_triangles.tolist())}
    for tri in triangles[:: max(len(triangles) // 500, 1)]:
        k = corners[tuple(sorted(index[tri].tolist()))]
        for corner in tri:
            position = rig_triangles[k].tolist().index(index[corner])
            np.testing.assert_allclose([uv[corner, 0], 1.0 - uv[corner, 1]], rig_uv[k, position], atol=1e-6)
    pairs = {(int(i), round(float(u), 6), round(float(v), 6)) for i, (u, v) in zip(index, uv)}
    assert len(pairs) == len(index) > len(data.template)


def test_four_influences_costs_the_reported_error(builtin_rig, builtin_export, tmp_path):
    path8, params, report8 = builtin_export
    report4 = export_glb(params, builtin_rig, tmp_path / "four.glb", max_influences=4)
    glb = Glb(tmp_path / "four.glb")
    attributes = glb.doc["meshes"][0]["primitives"][0]["attributes"]
    assert "JOINTS_1" not in attributes and report4.influences == 4
    assert report4.truncated == int(((builtin_rig.rig.skin_weights > 0).sum(1) > 4).sum())
    frames = list(range(len(params)))
    error4 = reimport_error_cm(tmp_path / "four.glb", builtin_rig, params, frames)
    assert error4 == pytest.approx(report4.max_error_cm, rel=0.02, abs=1e-4)
    assert error4 > 5 * report8.max_error_cm and error4 > TOLERANCE_CM
    assert "4 influences" in report4.summary() and f"{report4.max_error_cm:.4f} cm" in report4.summary()


def test_larynx_targets_meet_their_bound(builtin_rig, tmp_path):
    """A clip that only slides the larynx: the re-imported mesh follows it within the reported bound, and a
    wider slide (or a tighter bound) needs more targets."""
    params = clip(builtin_rig, frames=30, amplitude=0.0, tau_amplitude=0.05)
    params.psi[:] = 0.0
    report = export_glb(params, builtin_rig, tmp_path / "l.glb", larynx_error_cm=0.005)
    assert report.larynx_error_cm <= 0.005
    error = reimport_error_cm(tmp_path / "l.glb", builtin_rig, params, list(range(0, 30, 3)))
    assert error <= 0.005 + 1e-4
    # The slide is centimetres: without it the mesh would be far off.
    rest = rig_mesh(builtin_rig, dataclasses.replace(params, tau=np.zeros_like(params.tau)), [7])
    assert np.linalg.norm(rest - rig_mesh(builtin_rig, params, [7]), axis=-1).max() > 0.3
    narrow = larynx_targets(builtin_rig, 0.3 * params.tau, params.eta, 0.005)
    tight = larynx_targets(builtin_rig, params.tau, params.eta, 0.001)
    assert len(narrow.taus) < report.larynx_targets < len(tight.taus)
    constant = larynx_targets(builtin_rig, np.full(5, 0.01), np.ones(5), 0.005)
    assert len(constant.taus) == 1 and constant.error_cm == 0.0


@pytest.fixture(scope="module")
def real_export(real_rig, tmp_path_factory):
    params = clip(real_rig, frames=6)
    path = tmp_path_factory.mktemp("glb") / "hack.glb"
    return path, params, export_glb(params, real_rig, path)


@pytest.mark.shared
def test_validator_on_the_real_rig(validator, real_export):
    report = validator(real_export[0])[0]
    assert report["errors"] == 0 and report["warnings"] == 0, report["messages"]


@pytest.mark.shared
def test_reimport_reproduces_the_real_rig(real_rig, real_export):
    path, params, report = real_export
    assert report.rig_vertices == HACK_VERTICES and report.vertices == HACK_UV_PAIRS
    assert reimport_error_cm(path, real_rig, params, [0, 2, 5]) < TOLERANCE_CM
    # 9,708 of the release's vertices have more than 4 influences above 1e-6 (the count)
    weights = real_rig.rig.skin_weights
    assert int(((weights > 1e-6).sum(1) > 4).sum()) == 9708
    four = build_glb(params, real_rig, max_influences=4).report
    assert four.truncated == int(((weights > 0).sum(1) > 4).sum()) and four.max_error_cm > TOLERANCE_CM


@pytest.fixture(scope="module")
def giraffe(builtin_rig):
    from scene.characters import build_giraffe

    return HeadNeckModel(build_giraffe(builtin_rig.rig))


def test_giraffe_is_just_another_rig(giraffe, builtin_rig, tmp_path, validator):
    """The giraffe built from the built-in rig: named by character=, exported, valid, re-imported."""
    params = clip(giraffe, frames=6)
    source = tmp_path / "giraffe_params.npz"
    save_params(source, params)
    resolved = resolve_rig(params, source, character="giraffe")
    assert rig_checksum(resolved.rig) == rig_checksum(giraffe.rig)
    with pytest.raises(InputError, match="checksum"):
        resolve_rig(params, source)                  # the built-in rig is not the giraffe
    report = export_glb(params, resolved, tmp_path / "giraffe.glb")
    assert reimport_error_cm(tmp_path / "giraffe.glb", giraffe, params, [0, 3, 5]) < TOLERANCE_CM
    glb = Glb(tmp_path / "giraffe.glb")
    height_m = np.ptp(glb.accessor(glb.doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"])[:, 1])
    assert height_m == pytest.approx(np.ptp(giraffe.rig.template[:, 1]) / 100, rel=1e-5)
    assert height_m > 1.5 * np.ptp(builtin_rig.rig.template[:, 1]) / 100      # a long neck, at its size
    assert report.influences == 4       # its weights bind each vertex to adjacent bones only
    assert validator(tmp_path / "giraffe.glb")[0]["errors"] == 0


def test_bad_input(builtin_rig, turned_rig, tmp_path):
    params = clip(builtin_rig, frames=4)
    with pytest.raises(InputError, match="max_influences=5"):
        export_glb(params, builtin_rig, tmp_path / "x.glb", max_influences=5)
    late = clip(builtin_rig, frames=4, start=-0.5)
    with pytest.raises(InputError, match=r"clip\.npz: time starts at -0\.5 s"):
        export_glb(late, builtin_rig, tmp_path / "x.glb", source="clip.npz")
    # 1e6 s + 1 ms: the same float32 time
    close = dataclasses.replace(params, time=np.array([0.0, 1e6, 1e6 + 1e-3, 1e6 + 2e-3]))
    with pytest.raises(InputError, match="frame 2 .*float32"):
        export_glb(close, builtin_rig, tmp_path / "x.glb")
    with pytest.raises(InputError, match="checksum"):
        export_glb(params, turned_rig, tmp_path / "x.glb")
    with pytest.raises(InputError, match="larynx_error_cm"):
        export_glb(params, builtin_rig, tmp_path / "x.glb", larynx_error_cm=0.0)
    assert not list(tmp_path.iterdir())      # nothing written, not even a temporary file


def test_command_line(builtin_rig, tmp_path, capsys):
    source = tmp_path / "params.npz"
    save_params(source, clip(builtin_rig, frames=5))
    run_cli("gltf", run, [f"source={source}", f"out={tmp_path / 'a.glb'}", "max_influences=4"])
    out = capsys.readouterr().out
    assert "4 influences" in out and "max vertex error" in out
    assert Glb(tmp_path / "a.glb").doc["asset"]["version"] == "2.0"
    for argv, message in ([f"source={source}", f"out={tmp_path / 'b.glb'}", "max_influences=6"], "max_influences=6"),\
                         ([f"out={tmp_path / 'b.glb'}"], "source"), \
                         ([f"source={tmp_path / 'none.npz'}", f"out={tmp_path / 'b.glb'}"], "none.npz: file not found"):
        with pytest.raises(SystemExit) as exit_:
            run_cli("gltf", run, argv)
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err
    assert not (tmp_path / "b.glb").exists()


def smooth_offset(rig: HeadNeckModel, seed: int = 0, amplitude_cm: float = 0.6) -> np.ndarray:
    """A smooth per-vertex offset [N,3] cm (a fitted person's shape): a few low-frequency waves over the
    template's extent, plus a widening of the neck."""
    rng = np.random.default_rng(seed)
    template = rig.rig.template.astype(np.float64)
    unit = (template - template.mean(0)) / np.ptp(template, axis=0).max()
    offset = np.zeros_like(template)
    for _ in range(4):
        frequency, phase = rng.normal(0, 3, 3), rng.uniform(0, 2 * np.pi)
        offset += rng.normal(0, 1, 3) * np.sin(unit @ frequency + phase)[:, None]
    offset *= amplitude_cm / np.abs(offset).max()
    offset[:, [0, 2]] += 0.3 * unit[:, [0, 2]]
    return offset.astype(np.float32)


def test_a_fitted_shape_exports_as_that_person(builtin_rig, tmp_path, capsys):
    """params with shape_offset -> python -m scene.gltf -> the GLB's mesh at each frame is the rig with the
    offset template posed (to 0.01 cm, the issue's round-trip bound), not the base rig's."""
    from data.assets import with_shape_offset

    offset = smooth_offset(builtin_rig)
    params = dataclasses.replace(clip(builtin_rig, frames=6), shape_offset=offset)
    source = tmp_path / "params.npz"
    save_params(source, params)
    run_cli("gltf", run, [f"source={source}", f"out={tmp_path / 'person.glb'}"])
    assert "max vertex error" in capsys.readouterr().out
    person = HeadNeckModel(with_shape_offset(builtin_rig.rig, offset))
    frames = [0, 2, 5]
    assert reimport_error_cm(tmp_path / "person.glb", person, params, frames) < 0.01
    assert reimport_error_cm(tmp_path / "person.glb", builtin_rig, params, frames) > 0.5 * np.abs(offset).max()
