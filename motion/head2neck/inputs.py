"""Head orientation inputs: rotation matrices, yaw/pitch/roll arrays and capture CSVs read as [T,3,3]
rotations, checked, and recentred on the first frame.
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from base.errors import InputError
from base.files import load_npy
from base.rotations import ypr_to_matrix
from data.expressions import read_expressions

INPUT_FORMATS = ("auto", "matrix", "ypr", "csv")
UNITS = {"rad": 1.0, "deg": np.pi / 180.0, "halfturn": np.pi}


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


def recentered(head: torch.Tensor) -> torch.Tensor:
    """Orientations [T,3,3] relative to the first frame's, in the head's own frame: M_0^T M_t.

    A capture M_t = C H_t holds the subject's offset C from the camera on the left (the docstring of
    motion.head2neck.cli);
    with H_0 = I, M_0^T M_t = H_t: a nod stays a nod however the subject sat."""
    return head[0].T @ head
