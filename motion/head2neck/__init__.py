"""Drive HACK's cervical spine from head orientations: ``python -m motion.head2neck``.

    python -m motion.head2neck input=rotations.npy out=theta.npy [checkpoint=runs/head2neck/<run>/checkpoints/last.pt]
    python -m motion.head2neck input=ypr.npy input_format=ypr head_units=deg out=theta.npy
    python -m motion.head2neck input=take.csv out=theta.npy recenter=true rig=hack_rig.npz  # Live Link Face / ARKit CSV

Settings: :class:`Head2NeckCli` (``configs/head2neck.yaml``).  ``checkpoint=default`` (the default) is the
shipped model (``models/pretrained``); the model holds nothing of a rig, so ``rig=`` (default: the built-in
rig) says whose bone frames theta is written in.

Output: theta ``[T,8,3]`` float32 (axis-angle radians per joint in its bone frame, ``models.rig``),
one row per input frame, written atomically.  A CSV is resampled to a uniform grid at its own rate from
its first timestamp (Live Link Face drops lost-tracking rows; their frames are interpolated), so row t
is time ``start + t / fps``; start and rate are printed.
The model's output is made exact by the correction step (``models.head2neck.predict_theta``); the
remaining head orientation error and any joints outside the limits are printed.

Inputs (``input_format=auto`` picks by suffix and shape):
- ``matrix``: ``.npy`` ``[T,3,3]`` head orientations in the rig's world frame (y up, face towards +z,
  x to the subject's left), relative to the rest pose: ``HeadNeckModel.head_rotation``'s definition.
- ``ypr``: ``.npy`` ``[T,3]`` yaw, pitch, roll in ``head_units`` (rad | deg | halfturn, 1 halfturn = 180 deg).
- ``csv``: an expression capture read by ``data.expressions.read_expressions`` with ``HeadYaw,
  HeadPitch, HeadRoll`` columns (its ``head_ypr``).

Yaw/pitch/roll convention (``base.rotations.ypr_to_matrix``), in the rig's world frame::

    R = Ry(yaw) @ Rx(pitch) @ Rz(roll)        (intrinsic: yaw, then pitch, then roll)

- yaw about +y (up): + turns the face towards the subject's left;
- pitch about +x (the subject's left): + is flexion, the face looks down;
- roll about +z (forward): + tilts the head towards the subject's right shoulder.
Each sign is the rig's joint convention (``base.rotations``) applied to the whole head.

ARKit / Live Link Face ``HeadYaw, HeadPitch, HeadRoll``: ARKit's face anchor frame is x towards the
face's own left, y up, z out of the face (Apple, ``ARFaceAnchor`` documentation), the rig's frame, so
a face anchor rotation relative to a neutral, camera-facing pose is directly a ``matrix`` input.
Unreal's ARKit face support (``AppleARKitFaceSupport``, ``ToBlendShapeMap``) converts that rotation to
Unreal's left-handed frame (``FAppleARKitConversion::ToFTransform``), takes its ``FRotator`` and, when
the face is not mirrored, negates yaw and roll.  Working that through, a head turn to the subject's
left gives ``HeadYaw > 0``, looking down ``HeadPitch > 0`` and a tilt to the right shoulder
``HeadRoll > 0``, and ``FRotator``'s yaw-pitch-roll order is the order above: the mapping is the
identity, ``(yaw, pitch, roll) = (HeadYaw, HeadPitch, HeadRoll)``.  Uncertain, hence the options:
- signs: a mirrored face (Unreal's ``FaceMirrored``) flips yaw and roll, and users report HeadPitch and
  HeadYaw inverted with the phone in landscape; ``yaw_sign``, ``pitch_sign``, ``roll_sign`` (+-1)
  flip them.  Check with a recording of a known turn, nod and tilt;
- units: Unreal's live stream divides degrees by 180 (``units=halfturn``); the Live Link Face CSVs we
  have (../shared/samples) hold radians: their eye yaw spans +-0.6, physiological only in radians
  (+-35 deg), and ``data.expressions`` reads head angles as radians.  Default ``head_units=rad``;
- neutral: the angles are relative to the phone, so a subject not facing the camera squarely has an
  offset C: the captured orientation is M_t = C H_t, H_t the head's turn relative to the body.
  ``recenter=true`` takes the first frame as the rest pose (H_0 = I, so C = M_0) and feeds
  H_t = M_0^T M_t.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from base.cli import REQUIRED, register_config, to_dataclass
from base.errors import InputError
from base.files import load_npy, save_npy
from base.rotations import ypr_to_matrix
from data.expressions import read_expressions
from data.joint_limits import within_limits
from models.checkpoint import load_model
from models.head2neck import head_error_deg, predict_theta
from models.pretrained import default_checkpoint
from models.rig import HeadNeckModel

INPUT_FORMATS = ("auto", "matrix", "ypr", "csv")
UNITS = {"rad": 1.0, "deg": np.pi / 180.0, "halfturn": np.pi}


@dataclass
class Head2NeckCli:
    """``python -m motion.head2neck``: head orientations -> theta [T,8,3] (see the module docstring)."""

    input: str = REQUIRED              # .npy [T,3,3] head orientations, .npy [T,3] yaw/pitch/roll, or a capture .csv
    out: str = REQUIRED                # theta .npy [T,8,3], bone frames of ``rig``
    checkpoint: str = "default"        # default (the shipped model) | a head2neck checkpoint from train.py
    input_format: str = "auto"         # auto | matrix | ypr | csv
    head_units: str = "rad"            # yaw/pitch/roll units: rad | deg | halfturn (Unreal's live values, 1 = 180 deg)
    yaw_sign: float = 1.0              # flip HeadYaw/Pitch/Roll (mirrored capture, landscape phone): +1 or -1
    pitch_sign: float = 1.0
    roll_sign: float = 1.0
    recenter: bool = False             # make the first frame the rest pose (orientations relative to it)
    fps: float | None = None        # frame rate of a CSV without a time column
    timecode_fps: float | None = None  # Live Link Face timecode rate, for takes under a second
    rig: str | None = None          # rig file (python -m data.assets) whose bone frames theta is in; null = built-in
    iterations: int = 3                # at most this many Gauss-Newton steps of the exact correction
    threads: int = 1                   # enough for a capture; more threads only pay on an idle machine

    def __post_init__(self) -> None:
        if self.input_format not in INPUT_FORMATS:
            raise ValueError(f"input_format={self.input_format}: expected one of {', '.join(INPUT_FORMATS)}")
        if self.head_units not in UNITS:
            raise ValueError(f"head_units={self.head_units}: expected one of {', '.join(UNITS)}")
        for name in ("yaw_sign", "pitch_sign", "roll_sign"):
            if float(getattr(self, name)) not in (1.0, -1.0):
                raise ValueError(f"{name}={getattr(self, name)}: expected +1 or -1")
        if self.iterations < 0:
            raise ValueError(f"iterations={self.iterations}: expected a non-negative number of steps")


register_config("head2neck_schema", Head2NeckCli)


def check_rotations(matrices: np.ndarray, path: Path, tolerance: float = 1e-3) -> None:
    """InputError naming the first frame that is not a rotation matrix."""
    gram = np.einsum("tki,tkj->tij", matrices, matrices) - np.eye(3)
    bad = (np.abs(gram).max((1, 2)) > tolerance) | (np.linalg.det(matrices) < 0)
    if bad.any():
        frame = int(np.argmax(bad))
        raise InputError(f"{path}: frame {frame} is not a rotation matrix (R^T R - I up to "
                         f"{np.abs(gram[frame]).max():.3g}, det {np.linalg.det(matrices[frame]):.3g}); "
                         f"expected head orientations [T,3,3]")


def head_rotations_from_ypr(ypr: np.ndarray, units: str = "rad", signs: tuple[float, float, float] = (1.0, 1.0, 1.0),
                           label: str = "yaw/pitch/roll") -> torch.Tensor:
    """Head orientations [T,3,3] (float32) from yaw, pitch, roll [T,3] in ``units``, times ``signs``."""
    if units not in UNITS:
        raise InputError(f"units={units}: expected one of {', '.join(UNITS)}")
    radians = np.asarray(ypr, dtype=np.float64) * UNITS[units] * np.asarray(signs, dtype=np.float64)
    if len(radians) and np.abs(radians).max() > np.pi + 1e-6:
        raise InputError(f"{label}: angles up to {np.abs(radians).max():.3g} rad after units={units}; "
                         f"expected at most pi (wrong units?)")
    return ypr_to_matrix(torch.tensor(radians, dtype=torch.float32))


def read_head_rotations(path: str | Path, input_format: str = "auto", units: str = "rad",
                        signs: tuple[float, float, float] = (1.0, 1.0, 1.0), fps: float | None = None,
                        timecode_fps: float | None = None) -> tuple[torch.Tensor, str]:
    """Head orientations [T,3,3] (float32) from a file, and a description of what was read."""
    path = Path(path)
    if input_format not in INPUT_FORMATS:
        raise InputError(f"input_format={input_format}: expected one of {', '.join(INPUT_FORMATS)}")
    if input_format == "auto" and path.suffix.lower() not in (".csv", ".npy"):
        raise InputError(f"{path}: unsupported input '{path.suffix}', expected .npy ([T,3,3] or [T,3]) or .csv")
    if input_format == "csv" or (input_format == "auto" and path.suffix.lower() == ".csv"):
        track = read_expressions(path, fps=fps, timecode_fps=timecode_fps)
        if track.head_ypr is None:
            raise InputError(f"{path}: no head rotation recorded (HeadYaw, HeadPitch, HeadRoll missing or all "
                             f"zero); expected a capture with head rotation")
        uniform = track.resampled(track.fps)
        description = (f"{len(uniform)} frames of HeadYaw/HeadPitch/HeadRoll at {uniform.fps:g} fps from "
                       f"{uniform.time[0]:.3f} s ({len(track)} rows, resampled to the uniform grid)")
        return head_rotations_from_ypr(uniform.head_ypr, units, signs, str(path)), description
    array = load_npy(path, (2, 3), "head orientations [T,3,3] or yaw/pitch/roll [T,3]")
    if len(array) == 0:
        raise InputError(f"{path}: no frames (shape {array.shape}); expected head orientations [T,3,3] or "
                         f"yaw/pitch/roll [T,3] with T >= 1")
    if input_format == "auto":
        input_format = "matrix" if array.ndim == 3 else "ypr"
    if input_format == "matrix":
        if array.ndim != 3 or array.shape[1:] != (3, 3):
            raise InputError(f"{path}: array of shape {array.shape}, expected head orientations [T,3,3]")
        check_rotations(array, path)
        return torch.tensor(array, dtype=torch.float32), f"{len(array)} head orientations"
    if array.ndim != 2 or array.shape[1] != 3:
        raise InputError(f"{path}: array of shape {array.shape}, expected yaw, pitch, roll [T,3] in {units}")
    return head_rotations_from_ypr(array, units, signs, str(path)), f"{len(array)} yaw/pitch/roll frames"


def load_head2neck(checkpoint: str | Path, rig_path: str | Path | None = None) -> tuple[torch.nn.Module, HeadNeckModel]:
    """A head2neck model (``"default"``: the shipped one) and the rig ``rig_path`` (None: the built-in rig).

    The model holds nothing of a rig (``models.head2neck``): it reads the rig's joint rest frames when it
    runs, so any rig with HACK's 8-joint cervical chain serves."""
    if str(checkpoint) == "default":
        checkpoint = default_checkpoint("head2neck")
    model, _ = load_model(checkpoint, task="head2neck")
    return model, HeadNeckModel.from_config(rig_path)


def recentered(head: torch.Tensor) -> torch.Tensor:
    """Orientations [T,3,3] relative to the first frame's, in the head's own frame: M_0^T M_t.

    A capture M_t = C H_t holds the subject's offset C from the camera on the left (module doc);
    with H_0 = I, M_0^T M_t = H_t: a nod stays a nod however the subject sat."""
    return head[0].T @ head


def run(cfg: DictConfig) -> np.ndarray:
    """The CLI's work: returns theta [T,J,3] and writes it to ``cfg.out``."""
    cfg = to_dataclass(cfg, Head2NeckCli, where="configs/head2neck.yaml")
    model, rig = load_head2neck(cfg.checkpoint, cfg.rig)
    signs = (float(cfg.yaw_sign), float(cfg.pitch_sign), float(cfg.roll_sign))
    head, description = read_head_rotations(cfg.input, cfg.input_format, cfg.head_units, signs, cfg.fps,
                                            cfg.timecode_fps)
    if cfg.recenter:
        head = recentered(head)
    theta = predict_theta(model, rig, head, int(cfg.iterations))
    anatomical = rig.to_anatomical(theta)
    error = head_error_deg(anatomical, head, rig)
    outside = ~within_limits(anatomical)
    save_npy(cfg.out, theta.numpy().astype(np.float32))
    print(f"{cfg.input}: {description} -> {cfg.out} theta {list(theta.shape)}")
    print(f"head orientation residual: max {float(error.max()):.4f} deg, mean {float(error.mean()):.5f} deg")
    if outside.any():
        frames = torch.nonzero(outside.any(-1)).reshape(-1)
        print(f"joints outside the limits: {int(outside.sum())} in {len(frames)} frames (first: frame "
              f"{int(frames[0])})")
    else:
        print("joints outside the limits: none")
    return theta.numpy()
