"""The compact rig file: :class:`RigData`, every array a head-and-neck rig is, saved and loaded as ``.npz``."""
from __future__ import annotations

import dataclasses
import os
from dataclasses import MISSING, dataclass, field, fields
from pathlib import Path

import numpy as np

from base.errors import InputError
from base.files import save_npz

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


def with_shape_offset(rig: RigData, offset: np.ndarray | None, source: str = "shape_offset") -> RigData:
    """The person's rig: a copy of ``rig`` whose template is ``template + offset`` ([N,3] cm, a fitted
    ``shape_offset``), everything else (joints, weights, expressions, larynx) shared; ``rig`` itself when
    ``offset`` is None.  InputError naming ``source`` when the offset is not [N,3] finite numbers."""
    if offset is None:
        return rig
    offset = np.asarray(offset)
    if offset.shape != rig.template.shape:
        raise InputError(f"{source}: shape_offset of shape {list(offset.shape)}, expected "
                         f"{list(rig.template.shape)} (one offset per vertex of the rig)")
    if not np.isfinite(offset).all():
        vertex = int(np.argwhere(~np.isfinite(offset))[0, 0])
        raise InputError(f"{source}: shape_offset is not finite at vertex {vertex}")
    template = (rig.template.astype(np.float64) + offset).astype(rig.template.dtype)
    return dataclasses.replace(rig, template=template)
