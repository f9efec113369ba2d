"""Rig assets: the compact rig file, and its conversion from the HACK release and ICT-FaceKit.

    python -m data.assets hack_dir=PATH/HACK-Model ict_dir=PATH/ICT-FaceKit out=rig.npz

reads the official release (``model/000_generic_neutral_mesh_newuv.obj``,
``bones_neutral.json``, ``weight_map_smooth.npy``, ``Lc_mid.png``,
``ts_larynx.npy``; optionally ``P.npy`` pose correctives) and ICT-FaceKit's
``FaceXModel/`` OBJs, and writes one ``.npz`` that loads in a fraction of a
second.  The release is third-party data: keep the rig file outside the
repository and point the tools at it (``rig=...``).

Conventions (shared with ``models.rig``): mesh in cm, y up, face towards +z.
Bones follow the release's Blender layout: a bone's rest transform relative
to its parent ("local to parent", L2P) is ``[matrix | head + (0, parent
length, 0)]``, i.e. the bone's origin sits at its ``head`` offset from the
parent's *tail*, and its y axis runs along the bone.  The 55 expressions are
ICT's shapes except ``PupilDilate_L/R``, in sorted name order, taken over the
first N (template) vertices as deltas from ICT's neutral mesh.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path

import numpy as np

from base.cli import REQUIRED, register_config
from base.errors import InputError
from base.files import save_npz
from data.expressions import EXPRESSION_NAMES
from data.mesh_io import read_obj
from data.normals import stored_to_unit

JOINT_NAMES: tuple[str, ...] = ("c7t1", "c6c7", "c5c6", "c4c5", "c3c4", "c2c3", "c1c2", "oc1")
RIG_FORMAT_VERSION = 1

# Where a vertex without any face samples the larynx map: outside it, so the
# border-padded sampling of the release applies (its grid value 2 in [-1, 1]).
NO_UV = (1.5, -0.5)


@dataclass
class RigData:
    """Everything a head-and-neck rig is, as numpy arrays (see ``models.rig`` for the model).

    template:          [N,3]    neutral vertices, cm, without the larynx term.
    faces:             [F,k]    polygon vertex indices (k = 3 or 4), 0-based.
    vertex_uv:         [N,2]    UV of each vertex in the larynx map (u right, v up), ``NO_UV`` if none.
    joint_names:       [J]      root to head.
    parents:           [J]      parent index, -1 for the root.
    joint_rest_local:  [J,4,4]  rest transform of each bone relative to its parent (L2P).
    skin_weights:      [N,J]    linear blend skinning weights, rows sum to 1.
    expression_names:  [E]
    expression_deltas: [E,N,3]  blendshape offsets, cm.
    larynx_maps:       [K,H,W]  larynx displacement maps in UV space (row 0 = top = v 1), values ~[0,1].
    larynx_direction:  [3]      displacement direction of the larynx term (the release's ``ts``).
    uv_coords, faces_uv:        texture coordinates and per-corner indices for mesh export (optional).
    pose_correctives:  [J*9,N*3] SMPL-style pose blendshapes on (R - I) features, or empty.
    shape_deltas:      [S,N,3]  identity shape basis, or empty.
    """

    template: np.ndarray
    faces: np.ndarray
    vertex_uv: np.ndarray
    joint_names: np.ndarray
    parents: np.ndarray
    joint_rest_local: np.ndarray
    skin_weights: np.ndarray
    expression_names: np.ndarray
    expression_deltas: np.ndarray
    larynx_maps: np.ndarray
    larynx_direction: np.ndarray
    uv_coords: np.ndarray = field(default_factory=lambda: np.zeros((0, 2), np.float32))
    faces_uv: np.ndarray = field(default_factory=lambda: np.zeros((0, 3), np.int32))
    pose_correctives: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    shape_deltas: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3), np.float32))
    source: str = ""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Check shapes and invariants; raises InputError naming the offending array."""
        n = len(self.template)
        j = len(self.joint_names)
        checks = [
            (lambda: self.template.shape == (n, 3), f"template {self.template.shape}, expected [N,3]"),
            (lambda: self.faces.ndim == 2 and self.faces.shape[1] in (3, 4),
             f"faces {self.faces.shape}, expected [F,3|4]"),
            (lambda: self.faces.size == 0 or (self.faces.min() >= 0 and self.faces.max() < n),
             "faces index outside the vertices"),
            (lambda: self.vertex_uv.shape == (n, 2), f"vertex_uv {self.vertex_uv.shape}, expected [{n},2]"),
            (lambda: self.parents.shape == (j,), f"parents {self.parents.shape}, expected [{j}]"),
            (lambda: all(-1 <= p < i for i, p in enumerate(self.parents)), "parents must precede their children"),
            (lambda: self.joint_rest_local.shape == (j, 4, 4),
             f"joint_rest_local {self.joint_rest_local.shape}, expected [{j},4,4]"),
            (lambda: self.skin_weights.shape == (n, j), f"skin_weights {self.skin_weights.shape}, expected [{n},{j}]"),
            (lambda: np.allclose(self.skin_weights.sum(1), 1.0, atol=1e-4), "skin_weights rows must sum to 1"),
            (lambda: self.expression_deltas.shape == (len(self.expression_names), n, 3),
             f"expression_deltas {self.expression_deltas.shape}, expected [{len(self.expression_names)},{n},3]"),
            (lambda: self.larynx_maps.ndim == 3 and len(self.larynx_maps) >= 1,
             f"larynx_maps {self.larynx_maps.shape}, expected [K,H,W]"),
            (lambda: self.larynx_direction.shape == (3,),
             f"larynx_direction {self.larynx_direction.shape}, expected [3]"),
            (lambda: self.pose_correctives.size == 0 or self.pose_correctives.shape == (j * 9, n * 3),
             f"pose_correctives {self.pose_correctives.shape}, expected [{j * 9},{n * 3}] or empty"),
            (lambda: self.shape_deltas.size == 0 or self.shape_deltas.shape[1:] == (n, 3),
             f"shape_deltas {self.shape_deltas.shape}, expected [S,{n},3] or empty"),
        ]
        for ok, message in checks:  # in order: later checks assume the earlier shapes
            if not ok():
                raise InputError(f"rig {message}")

    def save(self, path: str | os.PathLike) -> None:
        arrays = {f.name: getattr(self, f.name) for f in fields(self)}
        arrays["source"] = np.array(self.source)
        arrays["format_version"] = np.array(RIG_FORMAT_VERSION)
        save_npz(path, **arrays)

    @classmethod
    def load(cls, path: str | os.PathLike) -> RigData:
        path = Path(path)
        if path.is_dir():
            raise InputError(
                f"{path}: is a folder; convert the release first: "
                f"python -m data.assets hack_dir={path} ict_dir=.../ICT-FaceKit out=rig.npz"
            )
        if not path.is_file():
            raise InputError(f"{path}: rig file not found (make one with python -m data.assets)")
        try:
            with np.load(path, allow_pickle=False) as z:
                stored = {k: z[k] for k in z.files}
        except Exception as e:  # numpy and zipfile raise many types for a truncated or damaged archive
            raise InputError(f"{path}: not a rig file, or a damaged one ({type(e).__name__}: {e}); "
                             f"make one with python -m data.assets") from None
        version = int(stored.pop("format_version", -1))
        if version != RIG_FORMAT_VERSION:
            raise InputError(f"{path}: rig format version {version}, expected {RIG_FORMAT_VERSION}; re-run data.assets")
        required = [f.name for f in fields(cls) if f.default is MISSING and f.default_factory is MISSING]
        missing = [name for name in required if name not in stored]
        if missing:
            raise InputError(f"{path}: rig file lacks {', '.join(missing)}")
        kwargs = {f.name: stored[f.name] for f in fields(cls) if f.name in stored and f.name != "source"}
        try:
            return cls(**kwargs, source=str(stored.get("source", path)))
        except InputError as e:
            raise InputError(f"{path}: {e}") from None


# --------------------------------------------------------------------------- release conversion


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


@dataclass
class AssetsCli:
    """``python -m data.assets``: the release and ICT-FaceKit folders, and the rig file to write."""

    hack_dir: str = REQUIRED
    ict_dir: str = REQUIRED
    out: str = "rig.npz"


register_config("assets_schema", AssetsCli)


def run(cfg) -> RigData:
    """``python -m data.assets``: convert and report."""
    started = time.perf_counter()
    rig = convert(cfg.hack_dir, cfg.ict_dir, cfg.out)
    print(f"wrote {cfg.out}: {len(rig.template)} vertices, {len(rig.faces)} faces, "
          f"{len(rig.joint_names)} joints, {len(rig.expression_names)} expressions, "
          f"{len(rig.larynx_maps)} larynx map(s) in {time.perf_counter() - started:.1f} s")
    return rig
