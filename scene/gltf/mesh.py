"""The mesh and skin as glTF stores them: vertices split at UV seams, normals of shapes, up to 8
influences per vertex.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from base.errors import InputError
from data.mesh_io import triangulate
from models.rig import HeadNeckModel
from scene.render import outward_faces, vertex_normals

METRES_PER_CM = 0.01
# Skin influences a glTF vertex carries: JOINTS_0/WEIGHTS_0 (4) and JOINTS_1/WEIGHTS_1 (4 more).
INFLUENCE_CHOICES = (4, 8)


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
