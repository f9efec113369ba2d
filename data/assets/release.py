"""Conversion of the HACK release and ICT-FaceKit into a :class:`data.assets.rig_data.RigData`."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from base.errors import InputError
from data.assets.rig_data import JOINT_NAMES, NO_UV, RigData
from data.expressions import EXPRESSION_NAMES
from data.mesh_io import read_obj
from data.normals import stored_to_unit


def _require(path: Path, what: str) -> Path:
    if not path.is_file():
        raise InputError(f"{path}: missing ({what})")
    return path


def rest_transforms_from_bones(bones: dict, path: Path) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Joint names, parents and L2P transforms [J,4,4] from the release's ``bones_neutral.json``."""
    names = list(bones)
    if tuple(names) != JOINT_NAMES:
        raise InputError(f"{path}: bones {names}, expected {list(JOINT_NAMES)} in this order")
    parents, local = [], []
    for name in names:
        bone = bones[name]
        for key in ("matrix", "head", "length", "parent"):
            if key not in bone:
                raise InputError(f"{path}: bone '{name}' has no '{key}'")
        parent = bone["parent"]
        if parent is not None and parent not in names[: names.index(name)]:
            raise InputError(f"{path}: bone '{name}' has parent '{parent}', expected an earlier bone or null")
        rotation = np.asarray(bone["matrix"], dtype=np.float64)
        if rotation.shape != (3, 3) or not np.allclose(rotation @ rotation.T, np.eye(3), atol=1e-5):
            raise InputError(f"{path}: bone '{name}' matrix is not a 3x3 rotation")
        offset = np.asarray(bone["head"], dtype=np.float64)
        if parent is not None:
            offset = offset + np.array([0.0, float(bones[parent]["length"]), 0.0])
        transform = np.eye(4)
        transform[:3, :3] = rotation
        transform[:3, 3] = offset
        parents.append(-1 if parent is None else names.index(parent))
        local.append(transform)
    return names, np.array(parents), np.stack(local)


def per_vertex_uv(num_vertices: int, faces: np.ndarray, faces_uv: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """UV of each vertex from its first face corner in file order (as the release does); ``NO_UV`` if none."""
    flat_v = faces.reshape(-1)
    flat_t = faces_uv.reshape(-1)
    first = np.full(num_vertices, -1)
    order = np.arange(len(flat_v))[::-1]  # assign in reverse so the first occurrence wins
    first[flat_v[order]] = flat_t[order]
    out = np.tile(np.array(NO_UV, dtype=np.float64), (num_vertices, 1))
    has = first >= 0
    out[has] = uv[first[has]]
    return out


def read_larynx_map(path: Path) -> np.ndarray:
    import cv2


    image = cv2.imread(str(_require(path, "larynx displacement map")), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: not a readable image (expected the grey larynx map)")
    if image.ndim == 3:
        image = cv2.cvtColor(image[..., :3], cv2.COLOR_BGR2GRAY)
    return stored_to_unit(image, str(path), np.float64)[0]


def read_ict_expressions(ict_dir: Path, num_vertices: int, template: np.ndarray) -> np.ndarray:
    """[55,N,3] expression deltas from ICT-FaceKit's FaceXModel OBJs (first N vertices)."""
    model_dir = ict_dir / "FaceXModel" if (ict_dir / "FaceXModel").is_dir() else ict_dir
    neutral_path = _require(model_dir / "generic_neutral_mesh.obj", "ICT-FaceKit neutral mesh")
    neutral = read_obj(neutral_path, vertices_only=True).vertices
    if len(neutral) < num_vertices:
        raise InputError(f"{neutral_path}: {len(neutral)} vertices, expected at least the template's {num_vertices}")
    neutral = neutral[:num_vertices]
    gap = np.abs(neutral - template).max()
    if gap > 0.1:  # the two files agree to ~0.002 cm; a different mesh is off by centimetres
        raise InputError(
            f"{neutral_path}: its first {num_vertices} vertices differ from the HACK template by up to {gap:.3g} cm; "
            "expected the ICT-FaceKit generic neutral mesh"
        )
    deltas = np.empty((len(EXPRESSION_NAMES), num_vertices, 3), dtype=np.float32)
    for k, name in enumerate(EXPRESSION_NAMES):
        path = _require(model_dir / f"{name}.obj", f"ICT-FaceKit expression '{name}'")
        vertices = read_obj(path, vertices_only=True).vertices
        if len(vertices) < num_vertices:
            raise InputError(f"{path}: {len(vertices)} vertices, expected at least {num_vertices}")
        deltas[k] = vertices[:num_vertices] - neutral
    return deltas


def convert(hack_dir: str | os.PathLike, ict_dir: str | os.PathLike, out: str | os.PathLike | None = None) -> RigData:
    """Read the HACK release (``hack_dir``, holding ``model/``) and ICT-FaceKit; optionally save to ``out``."""
    hack_dir = Path(hack_dir)
    model_dir = hack_dir / "model" if (hack_dir / "model").is_dir() else hack_dir
    if not model_dir.is_dir():
        raise InputError(f"{hack_dir}: not a folder (expected the HACK-Model release with a model/ folder)")
    bones_path = _require(model_dir / "bones_neutral.json", "bone rest poses")
    try:
        bones = json.loads(bones_path.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{bones_path}: malformed JSON ({e})") from None
    joint_names, parents, rest_local = rest_transforms_from_bones(bones, bones_path)

    mesh_path = _require(model_dir / "000_generic_neutral_mesh_newuv.obj", "template mesh with the larynx UVs")
    mesh = read_obj(mesh_path)
    if mesh.uv_coords is None or mesh.faces_uv is None:
        raise InputError(f"{mesh_path}: no texture coordinates; expected the '_newuv' template")
    n = len(mesh.vertices)

    weights_path = _require(model_dir / "weight_map_smooth.npy", "skinning weights")
    weights = np.load(weights_path).astype(np.float64)
    if weights.shape != (len(joint_names), n):
        raise InputError(f"{weights_path}: shape {weights.shape}, expected [{len(joint_names)},{n}]")
    totals = weights.sum(0)
    if (totals <= 0).any() or (weights < 0).any():
        raise InputError(f"{weights_path}: negative weights or a vertex with no weight "
                         f"(vertex {int(np.argmin(totals))})")
    weights = (weights / totals).T

    larynx = read_larynx_map(model_dir / "Lc_mid.png")
    direction_path = _require(model_dir / "ts_larynx.npy", "larynx displacement direction")
    direction = np.load(direction_path).astype(np.float64).reshape(-1)
    if direction.shape != (3,):
        raise InputError(f"{direction_path}: shape {direction.shape}, expected [3]")

    deltas = read_ict_expressions(Path(ict_dir), n, mesh.vertices)
    pose_correctives = np.zeros((0, 0), np.float32)
    if (model_dir / "P.npy").is_file():  # [J,3,3,N,3] in the release's layout, zero in the public release
        p = np.load(model_dir / "P.npy")
        if p.shape != (len(joint_names), 3, 3, n, 3):
            raise InputError(f"{model_dir / 'P.npy'}: shape {p.shape}, expected [{len(joint_names)},3,3,{n},3]")
        if np.abs(p).max() > 0:
            pose_correctives = p.reshape(len(joint_names) * 9, n * 3).astype(np.float32)

    rig = RigData(
        template=mesh.vertices.astype(np.float32),
        faces=mesh.faces.astype(np.int32),
        vertex_uv=per_vertex_uv(n, mesh.faces, mesh.faces_uv, mesh.uv_coords).astype(np.float32),
        joint_names=np.array(joint_names),
        parents=parents.astype(np.int64),
        joint_rest_local=rest_local,
        skin_weights=weights.astype(np.float32),
        expression_names=np.array(EXPRESSION_NAMES),
        expression_deltas=deltas,
        larynx_maps=larynx[None].astype(np.float32),
        larynx_direction=direction,
        uv_coords=mesh.uv_coords.astype(np.float32),
        faces_uv=mesh.faces_uv.astype(np.int32),
        pose_correctives=pose_correctives,
        source=f"HACK release {hack_dir.resolve()} + ICT-FaceKit {Path(ict_dir).resolve()}",
    )
    if out is not None:
        rig.save(out)
    return rig
