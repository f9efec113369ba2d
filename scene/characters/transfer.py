"""Deformation transfer (Sumner & Popovic 2004): blendshape deltas moved onto a mesh of the same topology."""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from data.mesh_io import triangulate

ZERO_DELTA_CM = 1e-5             # a vertex no source shape moves more than this is held fixed in the transfer


def _frames(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sumner-Popovic frames V = [v1-v0, v2-v0, n/sqrt|n|] [T,3,3] (columns) and areas [T]."""
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    normal = np.cross(e1, e2)
    norm = np.linalg.norm(normal, axis=1)
    fourth = normal / np.sqrt(np.maximum(norm, 1e-30))[:, None]
    return np.stack([e1, e2, fourth], axis=2), 0.5 * norm


def deformation_transfer(source_rest: np.ndarray, source_deltas: np.ndarray, target_rest: np.ndarray,
                         faces: np.ndarray, gradient_weights: np.ndarray | None = None,
                         fixed: np.ndarray | None = None, pin_weights: np.ndarray | None = None) -> np.ndarray:
    """Move blendshape deltas from a source mesh onto a target of the same topology (Sumner & Popovic,
    "Deformation transfer for triangle meshes", SIGGRAPH 2004).

    Per triangle (quads split in two), the source's deformation gradient Q = V~ V^-1 (V the edge frame
    [v1-v0, v2-v0, n/sqrt|n|] at rest, V~ deformed) is applied to the target's rest edges E; the target's
    deformed vertices x minimise sum_t area_t |[x1-x0, x2-x0] - Q_t E_t|^2 with the ``fixed`` vertices held
    at rest.  One sparse least-squares system (its normal equations factored once, scipy.sparse.linalg.splu)
    solved for every shape and coordinate as right-hand sides.

    Args:
        source_rest: [N,3]; source_deltas: [E,N,3] (cm); target_rest: [N,3]; faces: [F,3|4].
        gradient_weights: [T] in [0,1] per triangle of ``triangulate(faces)`` or None: the source gradient
            is blended towards the identity, Q' = I + w (Q - I) (1 = transfer as is).
        fixed: [N] bool vertices held at rest; default: those no source shape moves more than ZERO_DELTA_CM
            (if there are none, the first vertex, which fixes the translation).
        pin_weights: [N] in [0,1] or None: adds sum_v pin_v * L_vv |x_v - rest_v|^2 (L_vv the vertex's diagonal
            in the normal equations, so a weight of 1 holds a vertex as firmly as its edges do): where the
            gradients are faded, this keeps the region at rest instead of merely undeformed (a long faded
            neck would otherwise swing rigidly with the head's shapes).
    Returns:
        [E,N,3] target deltas (float64).  On a target that is a uniform scaling s of the source they equal
        s * source_deltas (exactly, up to the solver).
    """
    source_rest = np.asarray(source_rest, np.float64)
    target_rest = np.asarray(target_rest, np.float64)
    deltas = np.asarray(source_deltas, np.float64)
    n = len(source_rest)
    tri = triangulate(np.asarray(faces))
    v_rest, _ = _frames(source_rest[tri])
    w_rest, target_area = _frames(target_rest[tri])
    good = (np.abs(np.linalg.det(v_rest)) > 1e-12) & (target_area > 1e-12)
    inverse = np.zeros_like(v_rest)
    inverse[good] = np.linalg.inv(v_rest[good])
    target_edges = w_rest[:, :, :2]                                              # [T,3,2]
    weights = np.ones(len(tri)) if gradient_weights is None else np.clip(np.asarray(gradient_weights), 0, 1)

    if fixed is None:
        fixed = np.linalg.norm(deltas, axis=2).max(0) <= ZERO_DELTA_CM if len(deltas) else np.ones(n, bool)
        if not fixed.any():
            fixed = np.zeros(n, bool)
            fixed[0] = True
    free = np.flatnonzero(~fixed)
    column = np.full(n, -1)
    column[free] = np.arange(len(free))

    # G [2T, N]: rows x_{k} - x_0 (k = 1, 2) of each triangle, scaled by sqrt(area).
    t_index = np.flatnonzero(good)
    scale = np.sqrt(target_area[t_index])
    rows = np.arange(2 * len(t_index))
    g = sp.csr_matrix(
        (np.concatenate([np.repeat(scale, 2), -np.repeat(scale, 2)]),
         (np.concatenate([rows, rows]),
          np.concatenate([tri[t_index][:, 1:].reshape(-1), np.repeat(tri[t_index, 0], 2)]))),
        shape=(len(rows), n))
    g_free = g[:, free].tocsc()
    normal = (g_free.T @ g_free).tocsc()
    if pin_weights is not None:
        pins = np.clip(np.asarray(pin_weights, np.float64)[free], 0.0, 1.0)
        normal = (normal + sp.diags(pins * normal.diagonal())).tocsc()
    solve = spla.splu(normal)

    out = np.zeros_like(deltas)
    for k in range(len(deltas)):
        deformed, _ = _frames((source_rest + deltas[k])[tri])
        gradient = deformed @ inverse                                            # [T,3,3]
        change = weights[:, None, None] * (gradient - np.eye(3))                # Q' - I
        wanted = np.einsum("tij,tjk->tki", change[t_index], target_edges[t_index])  # [T,2,3] edge changes
        rhs = g_free.T @ (scale[:, None, None] * wanted).reshape(-1, 3)          # fixed vertices: zero change
        out[k][free] = solve.solve(np.ascontiguousarray(rhs))
    return out
