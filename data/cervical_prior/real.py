"""Real theta sequences: :func:`load_theta_sequences` reads HACK-layout theta arrays (``data/theta_list.npy`` of the
release: ``[T,8,3]`` axis-angle radians per joint in its bone frame, ``models.rig`` convention), a file or a
folder of them.  They carry no frame rate, and need none: their one user, the head-to-neck mapping, is per frame.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError
from base.files import load_npy
from data.cervical_prior.invivo import NUM_JOINTS


@dataclass
class ThetaSequence:
    """A real pose sequence: theta [T,J,3] float32 axis-angle radians (bone frames), read from ``source``."""

    theta: np.ndarray
    source: str


MAX_JOINT_ANGLE = np.pi  # an axis-angle longer than pi is not a rotation vector in the canonical range


def theta_sequence_layout(num_joints: int = NUM_JOINTS) -> str:
    return f"cervical poses [T,{num_joints},3] (axis-angle radians per joint, HACK's data/theta_list.npy layout)"


def load_theta_sequence(path: str | os.PathLike, num_joints: int = NUM_JOINTS) -> ThetaSequence:
    """One ``.npy`` theta sequence ``[T,num_joints,3]``; bad shapes or values raise InputError naming the file."""
    path = Path(path)
    expected = theta_sequence_layout(num_joints)
    theta = load_npy(path, 3, expected)
    if theta.shape[1:] != (num_joints, 3) or len(theta) == 0:
        raise InputError(f"{path}: array of shape {theta.shape}, expected {expected}")
    norms = np.linalg.norm(theta, axis=-1)
    if (norms > MAX_JOINT_ANGLE + 1e-3).any():
        frame, joint = np.argwhere(norms > MAX_JOINT_ANGLE + 1e-3)[0]
        raise InputError(f"{path}: frame {frame}, joint {joint}: rotation of {norms[frame, joint]:.3g} rad, "
                         f"expected axis-angle radians (at most pi); degrees?")
    return ThetaSequence(theta.astype(np.float32), str(path))


def load_theta_sequences(path: str | os.PathLike, num_joints: int = NUM_JOINTS) -> list[ThetaSequence]:
    """A ``.npy`` file or a folder of them (searched recursively, sorted); each must be a theta sequence."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.rglob("*.npy"))
        if not files:
            raise InputError(f"{path}: folder holds no .npy files; expected {theta_sequence_layout(num_joints)}")
        return [load_theta_sequence(f, num_joints) for f in files]
    if not path.exists():
        raise InputError(f"{path}: not found; expected a .npy file or a folder of "
                         f"{theta_sequence_layout(num_joints)}")
    if path.suffix.lower() != ".npy":
        raise InputError(f"{path}: unsupported format '{path.suffix}', expected .npy "
                         f"{theta_sequence_layout(num_joints)}")
    return [load_theta_sequence(path, num_joints)]
