"""The arrays an export writes (:class:`ExportData`: mesh, skin, morphs, animation, float32 as stored),
and their evaluation against the rig's forward pass.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from base.errors import InputError
from base.rotations import axis_angle_to_matrix, matrix_to_quaternion, quaternion_to_matrix
from data.params import AnimationParams, check_rig
from models.rig import HeadNeckModel, forward_kinematics, linear_blend_skinning, skinning_transforms
from scene.characters import person_rig
from scene.gltf.mesh import METRES_PER_CM, Influences, SeamSplit, shape_normals, skin_influences, split_uv_seams
from scene.gltf.morphs import (
    DEFAULT_LARYNX_ERROR_CM,
    LarynxTargets,
    corrective_features,
    corrective_weights,
    larynx_targets,
)

# A morph-target delta below this (cm) counts as zero for sparse storage (float noise of the assets).
ZERO_DELTA_CM = 1e-6
ZERO_NORMAL_DELTA = 1e-5       # likewise for a change of a unit normal


def joint_rotations(theta: np.ndarray) -> np.ndarray:
    """theta [T,J,3] (axis-angle, bone frames) -> rotation matrices [T,J,3,3] float64."""
    return axis_angle_to_matrix(torch.as_tensor(np.asarray(theta, np.float64))).numpy()


def local_rotations(rig: HeadNeckModel, rotations: np.ndarray) -> np.ndarray:
    """Each joint node's local rotation per frame as glTF quaternions (x, y, z, w) [T,J,4] float32: the
    rest rotation relative to the parent times the joint's rotation [T,J,3,3] (:func:`joint_rotations`);
    unit length, and each joint's track kept on one hemisphere (q and -q are the same rotation; glTF
    interpolates between neighbours)."""
    rest = torch.as_tensor(np.asarray(rig.rig.joint_rest_local, np.float64)[:, :3, :3])
    wxyz = matrix_to_quaternion(rest[None] @ torch.as_tensor(rotations, dtype=torch.float64)).numpy()
    xyzw = wxyz[..., [1, 2, 3, 0]]
    for t in range(1, len(xyzw)):
        flip = (xyzw[t] * xyzw[t - 1]).sum(-1) < 0
        xyzw[t, flip] *= -1.0
    xyzw = xyzw / np.linalg.norm(xyzw, axis=-1, keepdims=True)
    return xyzw.astype(np.float32)


@dataclass
class ExportData:
    """The arrays an export writes (metres, float32 as stored), for checks and readers.

    positions [V,3]; normals [V,3] (unit, of the positions); targets [M,V,3]; normal_targets [M,V,3] (the
    change of the unit normals each target makes at weight 1); target_names [M]; morph_weights [T,M];
    rotations [T,J,4] (x,y,z,w); translations [J,3]; inverse_bind [J,4,4]; joints [V,K]; weights [V,K];
    times [T]; split: SeamSplit.
    """

    positions: np.ndarray
    normals: np.ndarray
    targets: np.ndarray
    normal_targets: np.ndarray
    target_names: list[str]
    morph_weights: np.ndarray
    rotations: np.ndarray
    translations: np.ndarray
    inverse_bind: np.ndarray
    joints: np.ndarray
    weights: np.ndarray
    times: np.ndarray
    split: SeamSplit


def check_params(params: AnimationParams, rig: HeadNeckModel, source: str = "params") -> np.ndarray:
    """The clip's frame times as float32 [T], after checking they suit glTF and the rig: InputError naming
    ``source`` and the frame otherwise (times from >= 0, strictly increasing once stored as float32;
    joints and expressions those of the rig)."""
    check_rig(params, rig.rig, source)
    times = np.asarray(params.time, np.float64).astype(np.float32)
    if times[0] < 0:
        raise InputError(f"{source}: time starts at {params.time[0]:g} s; glTF animations start at >= 0")
    steps = np.diff(times)
    if (steps <= 0).any():
        bad = int(np.argmax(steps <= 0)) + 1
        raise InputError(f"{source}: frame {bad} (t = {params.time[bad]:.9g} s) does not follow frame {bad - 1} "
                         f"once stored as float32; glTF animation times must increase strictly")
    return times


def export_data(params: AnimationParams, rig: HeadNeckModel, max_influences: int = 8,
                larynx_error_cm: float = DEFAULT_LARYNX_ERROR_CM, source: str = "params",
                morph_normals: bool = True) -> tuple[ExportData, Influences, LarynxTargets, np.ndarray]:
    """Everything :func:`export_glb` stores, as arrays: (ExportData, Influences, LarynxTargets, corrective
    feature indices [C]); ``normal_targets`` empty without ``morph_normals``.  ``rig``: the base rig (checked
    against the params' checksum); a fitted ``params.shape_offset`` is added to its template
    (``scene.characters.person_rig``)."""
    times = check_params(params, rig, source)
    rig = person_rig(rig, params, source)
    if not larynx_error_cm > 0:
        raise InputError(f"larynx_error_cm={larynx_error_cm}: expected a positive bound in cm")
    data = rig.rig
    split = split_uv_seams(rig)
    index = split.rig_index
    influences = skin_influences(np.asarray(data.skin_weights), max_influences)
    larynx = larynx_targets(rig, params.tau, params.eta, larynx_error_cm)
    features = corrective_features(rig)

    expressions = np.asarray(data.expression_deltas, np.float64)
    correctives = np.asarray(data.pose_correctives, np.float64).reshape(-1, len(data.template), 3)[features] \
        if len(features) else np.zeros((0, len(data.template), 3))
    deltas = np.concatenate([expressions, larynx.offsets, correctives])                  # [M,N,3] cm
    deltas[np.abs(deltas) < ZERO_DELTA_CM] = 0.0
    template = np.asarray(data.template, np.float64)
    normals = shape_normals(rig, template[None])[0]
    if morph_normals:
        normal_targets = shape_normals(rig, template[None] + deltas) - normals
        normal_targets[np.abs(normal_targets) < ZERO_NORMAL_DELTA] = 0.0
    else:
        normal_targets = np.zeros((0, len(template), 3))
    names = ([str(n) for n in data.expression_names] + [f"larynx_tau{t:+.5f}" for t in larynx.taus]
             + [f"corrective_{data.joint_names[f // 9]}_r{(f % 9) // 3}c{f % 3}" for f in features])
    rotations = joint_rotations(params.theta)
    weights = np.concatenate([np.asarray(params.psi, np.float64), larynx.weights(params.tau, params.eta),
                              corrective_weights(rotations, features)], axis=1)

    translations = (np.asarray(data.joint_rest_local, np.float64)[:, :3, 3] * METRES_PER_CM).astype(np.float32)
    inverse_bind = rig.rest_world_inverse.double().numpy()      # G_j(0)^-1, the rig's; glTF's metres below
    inverse_bind[:, :3, 3] *= METRES_PER_CM
    inverse_bind[:, 3] = (0.0, 0.0, 0.0, 1.0)
    export = ExportData(
        positions=(template[index] * METRES_PER_CM).astype(np.float32), normals=normals[index].astype(np.float32),
        targets=(deltas[:, index] * METRES_PER_CM).astype(np.float32),
        normal_targets=normal_targets[:, index].astype(np.float32), target_names=names,
        morph_weights=weights.astype(np.float32),
        rotations=local_rotations(rig, rotations), translations=translations,
        inverse_bind=inverse_bind.astype(np.float32),
        joints=influences.joints[index], weights=influences.weights[index], times=times, split=split)
    return export, influences, larynx, features


def evaluate_export(export: ExportData, parents, frames: np.ndarray | None = None) -> np.ndarray:
    """Posed glTF vertices [T',V,3] in metres from the stored arrays (morphs, then the skin through the rig's
    forward kinematics and linear blend skinning, ``models.rig.skinning``), float64.  frames: indices into
    the clip (default all)."""
    frames = np.arange(len(export.times)) if frames is None else np.asarray(frames)
    targets = torch.as_tensor(export.targets, dtype=torch.float64).reshape(len(export.targets), -1)
    weights = torch.as_tensor(export.morph_weights[frames], dtype=torch.float64)
    rest = torch.as_tensor(export.positions, dtype=torch.float64) + (weights @ targets).reshape(len(frames), -1, 3)
    xyzw = torch.as_tensor(export.rotations[frames], dtype=torch.float64)
    node_local = torch.eye(4, dtype=torch.float64).repeat(len(export.translations), 1, 1)
    node_local[:, :3, 3] = torch.as_tensor(export.translations, dtype=torch.float64)
    world = forward_kinematics(quaternion_to_matrix(xyzw[..., [3, 0, 1, 2]]), node_local, parents)
    transforms = skinning_transforms(world, torch.as_tensor(export.inverse_bind, dtype=torch.float64))
    dense = np.zeros((len(export.positions), len(export.translations)))   # [V,J] weights, the slots summed
    np.add.at(dense, (np.arange(len(dense))[:, None], export.joints), export.weights.astype(np.float64))
    return linear_blend_skinning(rest, torch.as_tensor(dense), transforms).numpy()


def rig_vertices(rig: HeadNeckModel, params: AnimationParams, frames: np.ndarray | None = None) -> np.ndarray:
    """The rig's own posed vertices [T',N,3] cm at ``frames`` of the clip (default all), float64."""
    frames = np.arange(len(params)) if frames is None else np.asarray(frames)
    with torch.no_grad():
        out = rig(torch.as_tensor(params.theta[frames]), torch.as_tensor(params.psi[frames]),
                  torch.as_tensor(params.tau[frames]), torch.as_tensor(params.eta[frames]))
    return out.double().numpy()


def export_error_cm(export: ExportData, rig: HeadNeckModel, params: AnimationParams, chunk: int = 32) -> float:
    """Largest vertex distance (cm) over all frames between the stored arrays' evaluation and the rig."""
    worst = 0.0
    for start in range(0, len(params), chunk):
        frames = np.arange(start, min(start + chunk, len(params)))
        ours = evaluate_export(export, rig.parents, frames) / METRES_PER_CM
        theirs = rig_vertices(rig, params, frames)[:, export.split.rig_index]
        worst = max(worst, float(np.linalg.norm(ours - theirs, axis=-1).max()))
    return worst
