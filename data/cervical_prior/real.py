"""Real theta sequences: :func:`load_theta_sequences` reads HACK-layout theta arrays (``data/theta_list.npy`` of the
release: ``[T,8,3]`` axis-angle radians per joint in its bone frame, ``models.rig`` convention) and fit outputs
(``params.npz`` of ``motion.fit``, ``data.params``: its theta, checked against the training rig), a file or a
folder of them (a folder of fit folders).  Their frame rate is not used: their one user, the head-to-neck
mapping, is per frame.  A fit holds ``theta[:, 0]`` (c7t1) at zero, its rotation folded into the placement.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError
from base.files import load_npy
from data.assets import RigData
from data.cervical_prior.invivo import NUM_JOINTS
from data.params import check_rig, load_params


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


def load_fitted_sequence(path: str | os.PathLike, num_joints: int = NUM_JOINTS, rig: RigData | None = None,
                         rig_key: str = "rig") -> ThetaSequence:
    """The theta of a fit's ``params.npz`` (``data.params.load_params``), checked against ``rig`` (the
    training ``rig=``, named ``rig_key`` in the error: checksum, joints, expressions) when given."""
    params = load_params(path)
    if rig is not None:
        check_rig(params, rig, path, rig_key)
    if params.theta.shape[1] != num_joints:
        raise InputError(f"{path}: theta for {params.theta.shape[1]} joints, expected {num_joints}")
    return ThetaSequence(params.theta.astype(np.float32), str(path))


def load_theta_sequences(path: str | os.PathLike, num_joints: int = NUM_JOINTS, rig: RigData | None = None,
                         rig_key: str = "rig") -> list[ThetaSequence]:
    """A ``.npy`` theta sequence, a fit's ``params.npz``, or a folder of them (searched recursively, sorted:
    ``*.npy`` and every ``params.npz``, e.g. a folder of ``motion.fit`` output folders).  ``rig``: the rig
    the poses are for; fit outputs are checked against it (their ``rig_checksum``)."""
    path = Path(path)
    expected = f"{theta_sequence_layout(num_joints)} or fit outputs (params.npz)"
    if path.is_dir():
        files = sorted([*path.rglob("*.npy"), *path.rglob("params.npz")])
        if not files:
            raise InputError(f"{path}: folder holds no .npy files or params.npz; expected {expected}")
        return [load_fitted_sequence(f, num_joints, rig, rig_key) if f.suffix.lower() == ".npz"
                else load_theta_sequence(f, num_joints) for f in files]
    if not path.exists():
        raise InputError(f"{path}: not found; expected a .npy file, a params.npz or a folder of {expected}")
    if path.suffix.lower() == ".npz":
        return [load_fitted_sequence(path, num_joints, rig, rig_key)]
    if path.suffix.lower() != ".npy":
        raise InputError(f"{path}: unsupported format '{path.suffix}', expected .npy "
                         f"{theta_sequence_layout(num_joints)} or a fit's params.npz")
    return [load_theta_sequence(path, num_joints)]
