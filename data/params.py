"""The per-frame animation file ``params.npz``: what drives a rig, frame by frame.

``infer.py`` writes it, ``motion.retarget`` reads it and writes one for the target character, and the
exporters (``scene.gltf``, ``scene.preview``) read it.  Arrays (strings as 0-d unicode arrays):

- ``time [T]`` float64 seconds from 0, strictly increasing; ``fps`` the rate (0-d float64);
- ``psi [T,55]`` expression weights (HACK names in sorted order, ``expression_names``);
- ``tau [T]`` larynx slide in UV units of the larynx map (+ = up); ``eta [T]`` larynx size (1 = generic);
- ``theta [T,8,3]`` axis-angle radians per joint in the bone frames of the rig named in ``rig``;
- ``head_rotation [T,3,3]`` the head's world rotation relative to rest (``HeadNeckModel.head_rotation``);
- ``joint_names [8]``, ``expression_names [55]``;
- ``rig``: ``builtin``, a rig file's path, or a character (``character:giraffe``); ``rig_checksum``: the
  sha256 of the rig's arrays (:func:`rig_checksum`), so a reader can check it poses the right rig;
- ``producers``: JSON of what made the tracks (``{"larynx": ..., "head2neck": ..., "tool": ...}``);
- optional, only in files made with audio (``infer.py audio=``; ``motion.voice``): ``f0 [T]`` the voice's
  fundamental frequency in Hz (0 = unvoiced) and ``tau_voice [T]`` the voice term, the part of ``tau``
  that pitch moves (UV units, zero-mean over the take; already included in ``tau``).  Files without them
  load with both None; a reader that does not know them ignores them;
- optional, only in files made by fitting the rig to a capture (``motion.fit``): ``root_rotation [T,3,3]``
  and ``root_translation [T,3]`` (cm), the rig's placement in the capture's frame, ``x_capture =
  root_rotation @ x_rig + root_translation`` (the capture converted to cm; ``theta[:, 0]`` is then held
  at zero, its rotation folded into the placement); ``fit_rms_mm [T]`` the fit's data term RMS per frame
  (mm); ``shape_offset [V,3]`` (cm) the person's offset of the rig's rest mesh: the person's rig is the
  rig with template + shape_offset (``data.assets.with_shape_offset``), everything else unchanged, and
  ``rig_checksum`` stays the base rig's.  Readers check the checksum against the base rig, then apply the
  offset (the exporters and ``motion.retarget`` do).  Absent: None.  ``head_rotation`` stays the
  rig-frame head pose (the placement excluded).  Whoever re-saves a file keeps these fields.
"""
from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from base.errors import InputError, require_file
from base.files import save_npz
from data.assets import RigData

ARRAY_KEYS = ("time", "fps", "psi", "tau", "eta", "theta", "head_rotation")
TEXT_KEYS = ("rig", "rig_checksum", "producers")
OPTIONAL_KEYS = ("f0", "tau_voice",  # [T] float32 each; only in files made with audio
                 "root_rotation", "root_translation", "fit_rms_mm", "shape_offset")  # fitted files (motion.fit)
FIT_KEYS = ("root_rotation", "root_translation", "fit_rms_mm", "shape_offset")
ROTATION_TOLERANCE = 1e-3  # root_rotation: |R^T R - I| and |det R - 1| at most this (float32 storage)


def rig_checksum(rig: RigData) -> str:
    """sha256 (hex) over the arrays that define how a rig deforms (template, faces, joints, weights,
    expressions, larynx, correctives): two rigs with equal checksums pose identically."""
    digest = hashlib.sha256()
    for name in ("template", "faces", "joint_rest_local", "parents", "skin_weights", "expression_deltas",
                 "larynx_maps", "larynx_direction", "vertex_uv", "pose_correctives", "shape_deltas"):
        array = np.ascontiguousarray(getattr(rig, name))
        digest.update(name.encode())
        digest.update(str(array.dtype).encode() + str(array.shape).encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


@dataclass
class AnimationParams:
    """Per-frame rig inputs at ``fps``.

    time [T] s, psi [T,E], tau [T], eta [T], theta [T,J,3] (bone frames of ``rig``), head_rotation [T,3,3];
    optional f0 [T] Hz (0 = unvoiced) and tau_voice [T] (the voice's share of tau); optional fit results
    root_rotation [T,3,3], root_translation [T,3] cm, fit_rms_mm [T], shape_offset [V,3] cm; None when absent.
    """

    time: np.ndarray
    fps: float
    psi: np.ndarray
    tau: np.ndarray
    eta: np.ndarray
    theta: np.ndarray
    head_rotation: np.ndarray
    joint_names: list[str]
    expression_names: list[str]
    rig: str = "builtin"
    rig_checksum: str = ""
    producers: dict = field(default_factory=dict)
    f0: np.ndarray | None = None
    tau_voice: np.ndarray | None = None
    root_rotation: np.ndarray | None = None
    root_translation: np.ndarray | None = None
    fit_rms_mm: np.ndarray | None = None
    shape_offset: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.time = np.asarray(self.time, dtype=np.float64)
        self.fps = float(self.fps)
        self.psi = np.asarray(self.psi, dtype=np.float32)
        self.tau = np.asarray(self.tau, dtype=np.float32)
        self.eta = np.asarray(self.eta, dtype=np.float32)
        self.theta = np.asarray(self.theta, dtype=np.float32)
        self.head_rotation = np.asarray(self.head_rotation, dtype=np.float32)
        self.joint_names = [str(n) for n in self.joint_names]
        self.expression_names = [str(n) for n in self.expression_names]
        present = [name for name in OPTIONAL_KEYS if getattr(self, name) is not None]
        for name in present:
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float32))
        t, j, e = len(self.time), len(self.joint_names), len(self.expression_names)
        shapes = {"f0": (t,), "tau_voice": (t,), "root_rotation": (t, 3, 3), "root_translation": (t, 3),
                  "fit_rms_mm": (t,)}
        if self.shape_offset is not None:
            v = self.shape_offset.shape[0] if self.shape_offset.ndim == 2 else -1
            shapes["shape_offset"] = (v, 3) if v > 0 else ("V", 3)
        expected = {"time": (t,), "psi": (t, e), "tau": (t,), "eta": (t,), "theta": (t, j, 3),
                    "head_rotation": (t, 3, 3), **{name: shapes[name] for name in present}}
        for name, shape in expected.items():
            if getattr(self, name).shape != shape:
                raise ValueError(f"{name} has shape {getattr(self, name).shape}, expected {list(shape)}")
        if t < 1:
            raise ValueError("no frames")
        if not self.fps > 0:
            raise ValueError(f"fps must be positive, got {self.fps}")
        if t > 1 and (np.diff(self.time) <= 0).any():
            raise ValueError(f"time must increase, but frame {int(np.argmax(np.diff(self.time) <= 0)) + 1} does not")
        for name in ("time", "psi", "tau", "eta", "theta", "head_rotation", *present):
            if not np.isfinite(getattr(self, name)).all():
                bad = np.argwhere(~np.isfinite(getattr(self, name)))[0]
                raise ValueError(f"{name} is not finite at index {tuple(bad.tolist())}")
        if self.f0 is not None and (self.f0 < 0).any():
            raise ValueError(f"f0 is negative at frame {int(np.argmax(self.f0 < 0))}; expected Hz, 0 = unvoiced")
        if self.root_rotation is not None:
            r = self.root_rotation.astype(np.float64)
            error = np.abs(r.transpose(0, 2, 1) @ r - np.eye(3)).max(axis=(1, 2)) + np.abs(np.linalg.det(r) - 1)
            if (error > ROTATION_TOLERANCE).any():
                raise ValueError(f"root_rotation at frame {int(np.argmax(error > ROTATION_TOLERANCE))} is not a "
                                 f"rotation (|R^T R - I| + |det R - 1| = {error.max():.3g}); expected rotations")
        if (self.root_rotation is None) != (self.root_translation is None):
            raise ValueError("root_rotation and root_translation go together (the placement); one is missing")

    def __len__(self) -> int:
        return len(self.time)


def save_params(path: str | os.PathLike, params: AnimationParams) -> None:
    """Write ``params`` to ``path`` (``.npz``) atomically; the optional arrays (``OPTIONAL_KEYS``) only when
    present."""
    params.__post_init__()  # shapes and values checked again: a caller may have changed the arrays
    optional = {name: getattr(params, name) for name in OPTIONAL_KEYS if getattr(params, name) is not None}
    save_npz(path, compressed=True, **optional, time=params.time, fps=np.float64(params.fps), psi=params.psi,
             tau=params.tau, eta=params.eta, theta=params.theta, head_rotation=params.head_rotation,
             joint_names=np.array(params.joint_names), expression_names=np.array(params.expression_names),
             rig=np.array(params.rig), rig_checksum=np.array(params.rig_checksum),
             producers=np.array(json.dumps(params.producers, sort_keys=True)))


def load_params(path: str | os.PathLike) -> AnimationParams:
    """Read a ``params.npz``; InputError naming the file and the key on missing or malformed content."""
    path = require_file(path)
    if path.suffix.lower() != ".npz":
        raise InputError(f"{path}: expected a params .npz (written by infer.py or motion.retarget)")
    try:
        with np.load(path, allow_pickle=False) as z:
            stored = {k: z[k] for k in z.files}
    except Exception as e:  # numpy and zipfile raise many types for a damaged archive
        raise InputError(f"{path}: not a readable .npz ({type(e).__name__}: {e})") from None
    missing = [k for k in ARRAY_KEYS + ("joint_names", "expression_names") if k not in stored]
    if missing:
        raise InputError(f"{path}: lacks {', '.join(missing)}; expected a params file written by infer.py")
    try:
        producers = json.loads(str(stored["producers"])) if "producers" in stored else {}
    except json.JSONDecodeError as e:
        raise InputError(f"{path}: key 'producers' is not JSON ({e})") from None
    try:
        return AnimationParams(
            time=stored["time"], fps=float(stored["fps"]), psi=stored["psi"], tau=stored["tau"], eta=stored["eta"],
            theta=stored["theta"], head_rotation=stored["head_rotation"],
            joint_names=list(stored["joint_names"]), expression_names=list(stored["expression_names"]),
            rig=str(stored.get("rig", "builtin")), rig_checksum=str(stored.get("rig_checksum", "")),
            producers=producers, **{name: stored[name] for name in OPTIONAL_KEYS if name in stored})
    except (ValueError, TypeError) as e:
        raise InputError(f"{path}: {e}") from None


def fit_fields(params: AnimationParams, shape: bool = True) -> dict:
    """The fit's optional fields of ``params`` as keyword arguments, for a reader that re-saves a clip
    (``shape``: with ``shape_offset``, which belongs to the rig the clip drives)."""
    return {name: getattr(params, name) for name in FIT_KEYS if shape or name != "shape_offset"}


def check_rig(params: AnimationParams, rig: RigData, source: str | os.PathLike, rig_key: str = "rig") -> None:
    """InputError unless ``rig`` is the rig whose bone frames ``params.theta`` is in (checksum, joints,
    expressions), naming ``source`` and the config key ``rig_key`` that chose the rig."""
    if list(rig.joint_names) != params.joint_names:
        raise InputError(f"{source}: theta is for joints {params.joint_names}, the rig has {list(rig.joint_names)}")
    if list(rig.expression_names) != params.expression_names:
        raise InputError(f"{source}: psi is for other expressions than the rig's ({len(params.expression_names)} "
                         f"vs {len(rig.expression_names)})")
    if params.rig_checksum and params.rig_checksum != rig_checksum(rig):
        raise InputError(f"{source}: made with rig '{params.rig}' (checksum {params.rig_checksum[:12]}...), but the "
                         f"rig given ({rig_key}=) has checksum {rig_checksum(rig)[:12]}...; give {rig_key}= the rig "
                         f"the file was made with")


def rig_path(params: AnimationParams, source: str | os.PathLike) -> str | None:
    """The rig recorded in ``params`` as a path for ``HeadNeckModel.from_config`` (None = built-in);
    InputError when the recorded rig file is gone."""
    if params.rig in ("", "builtin"):
        return None
    if params.rig.startswith("character:"):
        return params.rig
    if not Path(params.rig).is_file():
        raise InputError(f"{source}: made with rig file {params.rig}, which is not there; give rig=<that file>")
    return params.rig
