"""Animated glTF 2.0 (``.glb``) export of a rig driven by a ``params.npz``: Blender, Unity, three.js.

    python -m scene.gltf source=params.npz out=anim.glb [rig=rig.npz] [character=giraffe] [max_influences=8|4]

One binary glTF holds the character at its real size and its whole clip:

- units: glTF's metre (our centimetres / 100), y up, the face towards +z (the project's axes already);
- the mesh: positions and normals of the template, UVs (glTF's v runs down: ``1 - v``), triangles
  (quads fanned, wound counter-clockwise outside).  Vertices are split where the UV layout has seams
  (one glTF vertex per distinct (rig vertex, UV) pair); ``mesh.extras.rig_vertex_index`` [V] maps each
  glTF vertex back to the rig's vertex;
- the cervical skeleton: one node per joint (rest transform relative to the parent as translation +
  rotation), under a common root node, a skin with inverse bind matrices;
- skin weights: up to 8 influences per vertex (``JOINTS_0/WEIGHTS_0`` and ``JOINTS_1/WEIGHTS_1``), the
  largest kept and renormalised in float32; ``max_influences=4`` for engines limited to four, at the
  cost of the error the export report prints;
- morph targets (``mesh.extras.targetNames``): the expressions by name; the larynx slide as K targets
  ``L(eta=1, tau_k)`` at nodes spread over the clip's tau range, weighted ``eta * hat_k(tau)`` (linear
  interpolation in tau, K the fewest meeting ``larynx_error_cm``); the pose correctives, where the rig
  has any, one target per (R - I) feature with the feature as weight; each target also carries the
  change of the normals it makes (``morph_normals``);
- one animation at the clip's frame times: each joint's local rotation (unit quaternions, rest rotation
  times the rotation of theta) and the morph weights.

Identity shape (beta) is not in ``params.npz`` and is left at 0.  Targets that touch few vertices are
stored as sparse accessors.
"""
from __future__ import annotations

import json
import os
import time as timer
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pygltflib as gl
import torch
from omegaconf import MISSING

from base.cli import register_config, to_dataclass
from base.errors import InputError
from base.files import atomic_path
from base.rotations import axis_angle_to_matrix, matrix_to_quaternion
from data.mesh_io import triangulate
from data.params import AnimationParams, check_rig, load_params, rig_path
from models.rig import HeadNeckModel
from scene.characters import load_character
from scene.render import outward_faces, vertex_normals

METRES_PER_CM = 0.01
# Skin influences a glTF vertex carries: JOINTS_0/WEIGHTS_0 (4) and JOINTS_1/WEIGHTS_1 (4 more).
INFLUENCE_CHOICES = (4, 8)
# A morph-target delta below this (cm) counts as zero for sparse storage (float noise of the assets).
ZERO_DELTA_CM = 1e-6
ZERO_NORMAL_DELTA = 1e-5       # likewise for a change of a unit normal
DEFAULT_LARYNX_ERROR_CM = 0.01   # a fifth of the 0.05 cm the whole export is held to
MAX_LARYNX_TARGETS = 256
SKIN_COLOUR = [0.80, 0.62, 0.52, 1.0]


# ----------------------------------------------------------------------------- mesh


@dataclass
class SeamSplit:
    """The glTF vertex layout of a rig mesh.

    rig_index [V] rig vertex of each glTF vertex; uv [V,2] its texture coordinate (the rig's convention,
    v up); triangles [F,3] glTF vertex indices, counter-clockwise seen from outside.
    """

    rig_index: np.ndarray
    uv: np.ndarray
    triangles: np.ndarray


def split_uv_seams(rig: HeadNeckModel) -> SeamSplit:
    """One glTF vertex per distinct (rig vertex, UV index) pair of the triangulated faces.

    Uses the rig's ``faces_uv``/``uv_coords`` when it has them, else one vertex per rig vertex with its
    ``vertex_uv``.  Rig vertices in no face are appended (so every rig vertex has a glTF vertex).
    """
    data = rig.rig
    triangles = triangulate(np.asarray(data.faces))
    outward = outward_faces(rig.template, np.asarray(data.faces)).numpy()
    flip = not np.array_equal(outward, triangles)
    n = len(data.template)
    if data.faces_uv.size and data.uv_coords.size and data.faces_uv.shape == data.faces.shape:
        uv_triangles = triangulate(np.asarray(data.faces_uv))
        count = len(data.uv_coords)
        keys = triangles.reshape(-1).astype(np.int64) * count + uv_triangles.reshape(-1)
        unique, inverse = np.unique(keys, return_inverse=True)
        rig_index = unique // count
        uv = np.asarray(data.uv_coords, np.float64)[unique % count]
        split = inverse.reshape(-1, 3)
    else:
        rig_index = np.arange(n)
        uv = np.asarray(data.vertex_uv, np.float64)
        split = triangles.astype(np.int64)
    unused = np.setdiff1d(np.arange(n), rig_index)
    if len(unused):
        rig_index = np.concatenate([rig_index, unused])
        uv = np.concatenate([uv, np.clip(np.asarray(data.vertex_uv, np.float64)[unused], 0.0, 1.0)])
    if flip:
        split = split[:, [0, 2, 1]]
    return SeamSplit(rig_index.astype(np.int64), uv, np.ascontiguousarray(split))


def shape_normals(rig: HeadNeckModel, shapes: np.ndarray, chunk: int = 16) -> np.ndarray:
    """Unit area-weighted vertex normals [S,N,3] (float64) of shapes [S,N,3] cm on the rig's faces; (0, 0, 1)
    at vertices in no face."""
    triangles = outward_faces(rig.template, np.asarray(rig.rig.faces))
    out = np.empty(np.shape(shapes))
    with torch.no_grad():
        for start in range(0, len(shapes), chunk):
            out[start:start + chunk] = vertex_normals(torch.as_tensor(shapes[start:start + chunk], dtype=torch.float64),
                                                      triangles).numpy()
    out[np.linalg.norm(out, axis=-1) < 0.5] = (0.0, 0.0, 1.0)
    return out


# ----------------------------------------------------------------------------- skin


@dataclass
class Influences:
    """joints [N,K] joint indices (largest weight first, 0 where the weight is 0), weights [N,K] float32
    summing to 1 per vertex; truncated: how many vertices lost weight (more than K non-zero influences)."""

    joints: np.ndarray
    weights: np.ndarray
    truncated: int


def skin_influences(weights: np.ndarray, max_influences: int = 8) -> Influences:
    """The largest ``max_influences`` weights of each vertex, renormalised in float32.

    weights [N,J] rows summing to 1.  K is 4 if no vertex has more than 4 non-zero weights (or
    ``max_influences`` is 4), else 8.  The renormalised float32 weights are made to sum to 1 in float64
    within 1e-7 by putting the remainder on the largest weight.
    """
    if max_influences not in INFLUENCE_CHOICES:
        raise InputError(f"max_influences={max_influences}: expected one of {list(INFLUENCE_CHOICES)}")
    weights = np.asarray(weights, np.float64)
    num_vertices, num_joints = weights.shape
    nonzero = (weights > 0).sum(1)
    k = 4 if max_influences == 4 or nonzero.max() <= 4 else 8
    order = np.argsort(-weights, axis=1, kind="stable")[:, :k]
    if order.shape[1] < k:  # fewer joints than slots
        order = np.concatenate([order, np.zeros((num_vertices, k - order.shape[1]), order.dtype)], axis=1)
    kept = np.take_along_axis(weights, order, axis=1)
    if num_joints < k:
        kept[:, num_joints:] = 0.0
    kept = kept / kept.sum(1, keepdims=True)
    out = kept.astype(np.float32)
    out[:, 0] = (1.0 - out[:, 1:].astype(np.float64).sum(1)).astype(np.float32)
    joints = np.where(out > 0, order, 0)
    return Influences(joints.astype(np.int64), out, int((nonzero > k).sum()))


# ----------------------------------------------------------------------------- morph targets


@dataclass
class LarynxTargets:
    """The larynx slide as morph targets: taus [K] nodes; offsets [K,N,3] cm, L(eta=1, tau_k) at every rig
    vertex; error_cm the largest vertex error of the piecewise-linear interpolation between the nodes over
    the clip's tau range, times the clip's largest |eta|."""

    taus: np.ndarray
    offsets: np.ndarray
    error_cm: float

    def weights(self, tau: np.ndarray, eta: np.ndarray) -> np.ndarray:
        """Per-frame target weights [T,K]: eta times the linear-interpolation (hat) weights of tau [T]."""
        return np.asarray(eta, np.float64)[:, None] * hat_weights(self.taus, tau)


def hat_weights(nodes: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Linear-interpolation weights [T,K] of ``values`` [T] on increasing ``nodes`` [K] (clamped to the
    ends; one node: weight 1)."""
    nodes = np.asarray(nodes, np.float64)
    values = np.asarray(values, np.float64)
    out = np.zeros((len(values), len(nodes)))
    if len(nodes) == 1:
        out[:, 0] = 1.0
        return out
    clipped = np.clip(values, nodes[0], nodes[-1])
    right = np.clip(np.searchsorted(nodes, clipped, side="right"), 1, len(nodes) - 1)
    left = right - 1
    fraction = (clipped - nodes[left]) / (nodes[right] - nodes[left])
    rows = np.arange(len(values))
    out[rows, left] = 1.0 - fraction
    out[rows, right] += fraction
    return out


def larynx_region(rig: HeadNeckModel, tau: np.ndarray) -> np.ndarray:
    """L(eta=1, tau) [T,M,3] cm at ``rig.larynx_vertices``, float64."""
    with torch.no_grad():
        tau = torch.as_tensor(np.asarray(tau, np.float32))
        return rig.larynx_region_offsets(tau, torch.ones_like(tau)).double().numpy()


def larynx_targets(rig: HeadNeckModel, tau: np.ndarray, eta: np.ndarray,
                   max_error_cm: float = DEFAULT_LARYNX_ERROR_CM) -> LarynxTargets:
    """The fewest evenly spaced tau nodes over [min tau, max tau] of the clip whose linear interpolation
    reproduces the larynx term within ``max_error_cm`` (times max |eta|) at a dense tau grid (8 samples
    per texel row of the larynx map) and at the clip's own taus.  tau [T], eta [T].

    The count is found by doubling, then bisection (the error falls with the count, not strictly
    monotonically, so the result is checked); at most ``MAX_LARYNX_TARGETS``, the most accurate tried
    then.
    """
    tau = np.asarray(tau, np.float64)
    low, high = float(tau.min()), float(tau.max())
    scale = max(float(np.abs(eta).max()), 1e-12)
    rows = rig.larynx_maps.shape[1]
    if high - low < 1e-9:
        nodes, error = np.array([low]), 0.0
    else:
        dense = np.concatenate([np.linspace(low, high, int(np.ceil((high - low) * (rows - 1) * 8)) + 2), tau])
        exact = larynx_region(rig, dense)
        active = np.flatnonzero(np.abs(exact).max(axis=(0, 2)) > 0)   # vertices the slide moves at all
        exact = exact[:, active]
        tried: dict[int, float] = {}

        def error_of(count: int) -> float:
            if count not in tried:
                candidate = np.linspace(low, high, count)
                at_nodes = larynx_region(rig, candidate)[:, active]
                step = (high - low) / (count - 1)
                left = np.clip(np.floor((dense - low) / step).astype(int), 0, count - 2)
                fraction = ((dense - candidate[left]) / step)[:, None, None]
                approx = (1.0 - fraction) * at_nodes[left] + fraction * at_nodes[left + 1]
                tried[count] = float(np.linalg.norm(approx - exact, axis=-1).max()) * scale
            return tried[count]

        upper = 2
        while error_of(upper) > max_error_cm and upper < MAX_LARYNX_TARGETS:
            upper = min(2 * upper, MAX_LARYNX_TARGETS)
        lower = max(upper // 2, 2)
        while upper - lower > 1:
            middle = (lower + upper) // 2
            if error_of(middle) <= max_error_cm:
                upper = middle
            else:
                lower = middle
        passing = [k for k, e in tried.items() if e <= max_error_cm]
        count = min(passing) if passing else min(tried, key=tried.get)
        nodes, error = np.linspace(low, high, count), tried[count]
    offsets = np.zeros((len(nodes), rig.num_vertices, 3))
    offsets[:, rig.larynx_vertices.numpy()] = larynx_region(rig, nodes)
    return LarynxTargets(nodes, offsets, error)


def corrective_features(rig: HeadNeckModel) -> np.ndarray:
    """Indices of the pose-corrective features (entries of (R - I) per joint, root excluded) with a
    non-zero blendshape, [C]."""
    correctives = np.asarray(rig.rig.pose_correctives)
    if correctives.size == 0:
        return np.zeros(0, np.int64)
    used = np.abs(correctives).max(axis=1) > 0
    used[:9] = False  # the root's features are zeroed by the rig (pose_features)
    return np.flatnonzero(used)


def corrective_weights(rotations: np.ndarray, features: np.ndarray) -> np.ndarray:
    """Per-frame weights [T,C] of the corrective targets: the (R - I) entries ``features`` of the joint
    rotations [T,J,3,3]."""
    flat = (rotations - np.eye(3)).reshape(len(rotations), -1)
    return flat[:, features]


# ----------------------------------------------------------------------------- animation


def local_rotations(rig: HeadNeckModel, theta: np.ndarray) -> np.ndarray:
    """Each joint node's local rotation per frame as glTF quaternions (x, y, z, w) [T,J,4] float32: the
    rest rotation relative to the parent times the rotation of theta [T,J,3]; unit length, and each
    joint's track kept on one hemisphere (q and -q are the same rotation; glTF interpolates between
    neighbours)."""
    rest = torch.as_tensor(np.asarray(rig.rig.joint_rest_local, np.float64)[:, :3, :3])
    rotations = axis_angle_to_matrix(torch.as_tensor(np.asarray(theta, np.float64)))
    wxyz = matrix_to_quaternion(rest[None] @ rotations).numpy()
    xyzw = wxyz[..., [1, 2, 3, 0]]
    for t in range(1, len(xyzw)):
        flip = (xyzw[t] * xyzw[t - 1]).sum(-1) < 0
        xyzw[t, flip] *= -1.0
    xyzw = xyzw / np.linalg.norm(xyzw, axis=-1, keepdims=True)
    return xyzw.astype(np.float32)


def quaternion_matrices(xyzw: np.ndarray) -> np.ndarray:
    """glTF quaternions (x, y, z, w) [...,4] -> rotation matrices [...,3,3] (float64)."""
    q = np.asarray(xyzw, np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], -1),
        np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], -1),
        np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], -1),
    ], -2)


def node_world_matrices(translations: np.ndarray, rotations: np.ndarray, parents) -> np.ndarray:
    """World matrices [...,J,4,4] of a joint chain from local translations [J,3] and rotation matrices
    [...,J,3,3] (parents precede children; -1 = under the identity root)."""
    local = np.zeros(rotations.shape[:-2] + (4, 4))
    local[..., :3, :3] = rotations
    local[..., :3, 3] = translations
    local[..., 3, 3] = 1.0
    world = np.empty_like(local)
    for j, parent in enumerate(parents):
        world[..., j, :, :] = local[..., j, :, :] if parent < 0 else world[..., parent, :, :] @ local[..., j, :, :]
    return world


# ----------------------------------------------------------------------------- document


@dataclass
class ExportReport:
    """What an export wrote and how faithful it is.

    path; vertices (glTF) / rig_vertices; triangles; frames; fps; influences (per vertex in the file) and
    truncated (vertices that lost weight); expression_targets, larynx_targets, corrective_targets;
    tau_range (low, high); larynx_error_cm (the interpolation bound); max_error_cm: the largest vertex
    error over all frames of the file's own data (skin + morphs, float32) against the rig's forward pass
    (None if not checked); bytes; seconds.
    """

    path: Path | None
    vertices: int
    rig_vertices: int
    triangles: int
    frames: int
    fps: float
    influences: int
    truncated: int
    expression_targets: int
    larynx_targets: int
    corrective_targets: int
    tau_range: tuple[float, float]
    larynx_error_cm: float
    max_error_cm: float | None = None
    bytes: int = 0
    seconds: float = 0.0

    def summary(self) -> str:
        lines = [
            f"wrote {self.path}: {self.vertices} vertices ({self.rig_vertices} rig vertices, split at UV seams), "
            f"{self.triangles} triangles, {self.frames} frames at {self.fps:g} fps, {self.bytes / 1e6:.1f} MB "
            f"in {self.seconds:.2f} s",
            f"  skin: {self.influences} influences per vertex"
            + (f" ({self.truncated} vertices had more and were renormalised)" if self.truncated else ""),
            f"  morph targets: {self.expression_targets} expressions, {self.larynx_targets} larynx "
            f"(tau {self.tau_range[0]:+.4f} .. {self.tau_range[1]:+.4f}, interpolation error "
            f"{self.larynx_error_cm:.4f} cm), {self.corrective_targets} pose correctives",
        ]
        if self.max_error_cm is not None:
            lines.append(f"  max vertex error vs the rig over the clip: {self.max_error_cm:.4f} cm")
        return "\n".join(lines)


@dataclass
class _Builder:
    """Buffer views and accessors of one binary buffer."""

    gltf: gl.GLTF2
    chunks: list = field(default_factory=list)
    length: int = 0

    def view(self, data: np.ndarray, target: int | None = None) -> int:
        raw = np.ascontiguousarray(data).tobytes()
        pad = (-self.length) % 4
        if pad:
            self.chunks.append(b"\x00" * pad)
            self.length += pad
        self.gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=self.length, byteLength=len(raw),
                                                   target=target))
        self.chunks.append(raw)
        self.length += len(raw)
        return len(self.gltf.bufferViews) - 1

    def accessor(self, data: np.ndarray, kind: str, target: int | None = None, bounds: bool = False,
                 name: str | None = None) -> int:
        data = np.asarray(data)
        component = {np.dtype(np.float32): gl.FLOAT, np.dtype(np.uint8): gl.UNSIGNED_BYTE,
                     np.dtype(np.uint16): gl.UNSIGNED_SHORT, np.dtype(np.uint32): gl.UNSIGNED_INT}[data.dtype]
        accessor = gl.Accessor(bufferView=self.view(data, target), componentType=component, count=data.shape[0],
                               type=kind, name=name)
        self._bounds(accessor, data, kind, bounds)
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1

    def sparse_vec3(self, data: np.ndarray, name: str | None = None, bounds: bool = True) -> int:
        """A float32 VEC3 morph-target accessor [V,3], sparse when few rows are non-zero."""
        data = np.asarray(data, np.float32)
        rows = np.flatnonzero(np.abs(data).max(1) > 0)
        if len(rows) * 16 >= data.size * 4 * 0.75:
            return self.accessor(data, gl.VEC3, gl.ARRAY_BUFFER, bounds=bounds, name=name)
        accessor = gl.Accessor(componentType=gl.FLOAT, count=len(data), type=gl.VEC3, name=name, byteOffset=None)
        if len(rows):
            index_type = np.uint16 if len(data) < 2**16 else np.uint32
            accessor.sparse = gl.Sparse(
                count=len(rows),
                indices=gl.AccessorSparseIndices(bufferView=self.view(rows.astype(index_type)),
                                                 componentType=gl.UNSIGNED_SHORT if index_type is np.uint16
                                                 else gl.UNSIGNED_INT),
                values=gl.AccessorSparseValues(bufferView=self.view(data[rows])))
        self._bounds(accessor, data, gl.VEC3, bounds)
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1

    @staticmethod
    def _bounds(accessor: gl.Accessor, data: np.ndarray, kind: str, bounds: bool) -> None:
        if not bounds:
            accessor.min, accessor.max = None, None
            return
        flat = data.reshape(len(data), -1) if kind != gl.SCALAR else data.reshape(-1, 1)
        # float32 extremes as Python floats: exact, so the validator's min/max check holds
        accessor.min = [float(v) for v in flat.min(0)]
        accessor.max = [float(v) for v in flat.max(0)]

    def blob(self) -> bytes:
        raw = b"".join(self.chunks)
        return raw + b"\x00" * ((-len(raw)) % 4)


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
    feature indices [C]); ``normal_targets`` empty without ``morph_normals``."""
    times = check_params(params, rig, source)
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
    with torch.no_grad():
        rotation_matrices = axis_angle_to_matrix(torch.as_tensor(params.theta, dtype=torch.float32)).double().numpy()
    weights = np.concatenate([np.asarray(params.psi, np.float64), larynx.weights(params.tau, params.eta),
                              corrective_weights(rotation_matrices, features)], axis=1)

    rotations = local_rotations(rig, params.theta)
    translations = (np.asarray(data.joint_rest_local, np.float64)[:, :3, 3] * METRES_PER_CM).astype(np.float32)
    rest_rotations = quaternion_matrices(local_rotations(rig, np.zeros((1,) + params.theta.shape[1:]))[0])
    rest_world = node_world_matrices(translations.astype(np.float64), rest_rotations, rig.parents)
    inverse_bind = np.linalg.inv(rest_world)
    inverse_bind[:, 3] = (0.0, 0.0, 0.0, 1.0)
    export = ExportData(
        positions=(template[index] * METRES_PER_CM).astype(np.float32), normals=normals[index].astype(np.float32),
        targets=(deltas[:, index] * METRES_PER_CM).astype(np.float32),
        normal_targets=normal_targets[:, index].astype(np.float32), target_names=names,
        morph_weights=weights.astype(np.float32),
        rotations=rotations, translations=translations, inverse_bind=inverse_bind.astype(np.float32),
        joints=influences.joints[index], weights=influences.weights[index], times=times, split=split)
    return export, influences, larynx, features


def evaluate_export(export: ExportData, parents, frames: np.ndarray | None = None) -> np.ndarray:
    """Posed glTF vertices [T',V,3] in metres from the stored arrays (morphs, then skin), float64.
    frames: indices into the clip (default all)."""
    frames = np.arange(len(export.times)) if frames is None else np.asarray(frames)
    targets = export.targets.astype(np.float64).reshape(len(export.targets), -1)
    rest = export.positions[None].astype(np.float64) + (export.morph_weights[frames].astype(np.float64) @ targets) \
        .reshape(len(frames), -1, 3)
    world = node_world_matrices(export.translations.astype(np.float64),
                                quaternion_matrices(export.rotations[frames]), parents)
    joint_matrices = world @ export.inverse_bind.astype(np.float64)                       # [T,J,4,4]
    dense = np.zeros((len(export.positions), len(export.translations)))   # [V,J] weights, the slots summed
    rows = np.arange(len(export.positions))
    for slot in range(export.weights.shape[1]):
        np.add.at(dense, (rows, export.joints[:, slot]), export.weights[:, slot].astype(np.float64))
    by_joint = joint_matrices[:, :, :3, :].transpose(1, 0, 2, 3).reshape(len(export.translations), -1)
    blended = (dense @ by_joint).reshape(len(export.positions), len(frames), 3, 4).transpose(1, 0, 2, 3)
    return blended[..., 3] + blended[..., 0] * rest[..., 0:1] + blended[..., 1] * rest[..., 1:2] \
        + blended[..., 2] * rest[..., 2:3]


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


def build_gltf(export: ExportData, rig: HeadNeckModel, params: AnimationParams, extras: dict | None = None) -> gl.GLTF2:
    """The glTF document (with its binary blob set) of ``export``."""
    data = rig.rig
    gltf = gl.GLTF2(asset=gl.Asset(version="2.0", generator="hackneck scene.gltf (pygltflib)",
                                   extras=extras or {}))
    b = _Builder(gltf)
    split = export.split
    position = b.accessor(export.positions, gl.VEC3, gl.ARRAY_BUFFER, bounds=True, name="POSITION")
    normal = b.accessor(export.normals, gl.VEC3, gl.ARRAY_BUFFER, name="NORMAL")
    uv = np.stack([split.uv[:, 0], 1.0 - split.uv[:, 1]], axis=1).astype(np.float32)
    texcoord = b.accessor(uv, gl.VEC2, gl.ARRAY_BUFFER, name="TEXCOORD_0")
    attributes = gl.Attributes(POSITION=position, NORMAL=normal, TEXCOORD_0=texcoord)
    joint_type = np.uint8 if rig.num_joints <= 256 else np.uint16
    for slot in range(export.joints.shape[1] // 4):
        columns = slice(4 * slot, 4 * slot + 4)
        joint_slots = export.joints[:, columns].astype(joint_type)
        setattr(attributes, f"JOINTS_{slot}", b.accessor(joint_slots, gl.VEC4, gl.ARRAY_BUFFER, name=f"JOINTS_{slot}"))
        setattr(attributes, f"WEIGHTS_{slot}",
                b.accessor(export.weights[:, columns], gl.VEC4, gl.ARRAY_BUFFER, name=f"WEIGHTS_{slot}"))
    index_type = np.uint16 if len(export.positions) < 2**16 - 1 else np.uint32
    indices = b.accessor(split.triangles.reshape(-1).astype(index_type), gl.SCALAR, gl.ELEMENT_ARRAY_BUFFER,
                         name="indices")
    targets = [{"POSITION": b.sparse_vec3(target, name=name)} for target, name in zip(export.targets,
                                                                                      export.target_names)]
    for target, normal in zip(targets, export.normal_targets):
        target["NORMAL"] = b.sparse_vec3(normal, bounds=False)
    gltf.materials.append(gl.Material(name="skin", pbrMetallicRoughness=gl.PbrMetallicRoughness(
        baseColorFactor=SKIN_COLOUR, metallicFactor=0.0, roughnessFactor=0.6)))
    primitive = gl.Primitive(attributes=attributes, indices=indices, material=0, mode=gl.TRIANGLES,
                             targets=targets)
    gltf.meshes.append(gl.Mesh(name="head_neck", primitives=[primitive],
                               weights=[float(w) for w in export.morph_weights[0]],
                               extras={"targetNames": export.target_names,
                                       "rig_vertex_index": [int(i) for i in split.rig_index]}))

    # Nodes: 0 the skeleton's root, 1..J the joints, J+1 the skinned mesh (at the scene root).
    joints = list(range(1, rig.num_joints + 1))
    gltf.nodes.append(gl.Node(name="skeleton", children=[1 + j for j, p in enumerate(rig.parents) if p < 0]))
    for j, name in enumerate(data.joint_names):
        children = [1 + c for c, p in enumerate(rig.parents) if p == j]
        gltf.nodes.append(gl.Node(name=str(name), translation=[float(v) for v in export.translations[j]],
                                  rotation=[float(v) for v in export.rotations[0, j]], children=children or None))
    mesh_node = len(gltf.nodes)
    gltf.nodes.append(gl.Node(name="head_neck", mesh=0, skin=0))
    inverse_bind = np.transpose(export.inverse_bind, (0, 2, 1)).reshape(-1, 16)   # column-major
    gltf.skins.append(gl.Skin(name="cervical_spine", joints=joints, skeleton=0,
                              inverseBindMatrices=b.accessor(inverse_bind.astype(np.float32), gl.MAT4)))
    gltf.scenes.append(gl.Scene(name="hackneck", nodes=[0, mesh_node]))
    gltf.scene = 0

    times = b.accessor(export.times, gl.SCALAR, bounds=True, name="time")
    samplers, channels = [], []
    for j in range(rig.num_joints):
        samplers.append(gl.AnimationSampler(input=times, interpolation=gl.ANIM_LINEAR,
                                            output=b.accessor(export.rotations[:, j], gl.VEC4)))
        channels.append(gl.AnimationChannel(sampler=len(samplers) - 1,
                                            target=gl.AnimationChannelTarget(node=joints[j], path="rotation")))
    samplers.append(gl.AnimationSampler(input=times, interpolation=gl.ANIM_LINEAR,
                                        output=b.accessor(export.morph_weights.reshape(-1), gl.SCALAR)))
    channels.append(gl.AnimationChannel(sampler=len(samplers) - 1,
                                        target=gl.AnimationChannelTarget(node=mesh_node, path="weights")))
    gltf.animations.append(gl.Animation(name="clip", samplers=samplers, channels=channels,
                                        extras={"fps": float(params.fps)}))
    blob = b.blob()
    gltf.buffers.append(gl.Buffer(byteLength=len(blob)))
    gltf.set_binary_blob(blob)
    return gltf


def export_glb(params: AnimationParams, rig: HeadNeckModel, path: str | os.PathLike | None,
               max_influences: int = 8, larynx_error_cm: float = DEFAULT_LARYNX_ERROR_CM, check: bool = True,
               source: str = "params", morph_normals: bool = True) -> ExportReport:
    """Write the clip ``params`` on ``rig`` as one animated ``.glb`` at ``path`` (atomically; None: build
    only, for timing).

    Args:
        params: the per-frame inputs (``data.params.AnimationParams``) in the rig's bone frames.
        rig: the rig they drive.
        max_influences: 8 (JOINTS_0 + JOINTS_1) or 4 (engines limited to four; costs the reported error).
        larynx_error_cm: bound on the larynx morph-target interpolation error.
        check: evaluate the stored data at every frame against ``rig(...)`` (``ExportReport.max_error_cm``);
            always done when vertices lose influences.
        source: how to name the params in error messages (their file).
        morph_normals: store each morph target's change of the normals (for viewers' shading; about
            doubles the file; Blender recomputes normals and ignores them).
    Returns:
        ExportReport (``summary()`` prints it).
    """
    started = timer.perf_counter()
    export, influences, larynx, features = export_data(params, rig, max_influences, larynx_error_cm, source,
                                                       morph_normals)
    extras = {"units": "metre", "source_units": "cm", "up": "+y", "forward": "+z", "fps": float(params.fps),
              "rig": params.rig, "rig_checksum": params.rig_checksum, "producers": json.dumps(params.producers),
              "larynx_taus": [float(t) for t in larynx.taus]}
    gltf = build_gltf(export, rig, params, extras)
    raw = b"".join(gltf.save_to_bytes())
    if path is not None:
        path = Path(path)
        with atomic_path(path) as tmp:
            tmp.write_bytes(raw)
    report = ExportReport(
        path=path, vertices=len(export.positions), rig_vertices=rig.num_vertices,
        triangles=len(export.split.triangles), frames=len(params), fps=float(params.fps),
        influences=export.joints.shape[1], truncated=influences.truncated,
        expression_targets=len(rig.expression_names), larynx_targets=len(larynx.taus),
        corrective_targets=len(features), tau_range=(float(np.min(params.tau)), float(np.max(params.tau))),
        larynx_error_cm=larynx.error_cm, bytes=len(raw))
    report.seconds = timer.perf_counter() - started
    if check or influences.truncated:  # dropping influences always reports what it costs
        report.max_error_cm = export_error_cm(export, rig, params)
    return report


# ----------------------------------------------------------------------------- command line


@dataclass
class GltfConfig:
    """``python -m scene.gltf`` settings (``configs/gltf.yaml``).

    source: params.npz; out: the .glb; rig: a rig file overriding the one recorded in source;
    character: human | giraffe | a character file, built on ``rig`` (``scene.characters``); max_influences: 8 or 4;
    larynx_error_cm: larynx morph-target bound; check: evaluate the file's data against the rig;
    morph_normals: store the morph targets' normal changes.
    """

    source: str = MISSING
    out: str = MISSING
    rig: str | None = None
    character: str | None = None
    max_influences: int = 8
    larynx_error_cm: float = DEFAULT_LARYNX_ERROR_CM
    check: bool = True
    morph_normals: bool = True
    threads: int = 1

    def __post_init__(self) -> None:
        if self.max_influences not in INFLUENCE_CHOICES:
            raise ValueError(f"max_influences={self.max_influences}: expected one of {list(INFLUENCE_CHOICES)}")
        if not self.larynx_error_cm > 0:
            raise ValueError(f"larynx_error_cm={self.larynx_error_cm}: expected a positive bound in cm")


register_config("gltf_schema", GltfConfig)


def resolve_rig(params: AnimationParams, source: str | os.PathLike, rig: str | None = None,
                character: str | None = None) -> HeadNeckModel:
    """The rig ``params`` drive, checked against them (joints, expressions, checksum).

    ``character`` (``human``, ``giraffe`` or a character file; ``scene.characters.load_character``) built
    on ``rig`` (a rig file; default the built-in rig); else ``rig``; else the rig recorded in ``params``
    (a file, the built-in rig, or ``character:<name>`` built on the built-in rig).
    """
    key = "character" if character else "rig"
    if not character:
        choice = rig if rig else rig_path(params, source)
        if choice is not None and str(choice).startswith("character:"):
            character, key = str(choice).split(":", 1)[1], "rig"
        else:
            model = HeadNeckModel.from_config(choice)
            check_rig(params, model.rig, source, key)
            return model
    model = HeadNeckModel(load_character(character, HeadNeckModel.from_config(rig).rig))
    check_rig(params, model.rig, source, key)
    return model


def run(cfg) -> ExportReport:
    """``python -m scene.gltf``: export and print the report."""
    settings = to_dataclass(cfg, GltfConfig, where="scene.gltf")
    params = load_params(settings.source)
    rig = resolve_rig(params, settings.source, settings.rig, settings.character)
    report = export_glb(params, rig, settings.out, settings.max_influences, settings.larynx_error_cm,
                        settings.check, source=settings.source, morph_normals=settings.morph_normals)
    print(report.summary())
    return report
