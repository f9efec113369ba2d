"""The per-sequence shape offset: a smooth offset of the rest mesh that absorbs another person's head and neck.

After each step of the second and the last stage (``models.fit.sequence``), with the poses held, the offset
s [V,3] (cm) minimises

    sum_t sum_n w_tn |M_tn (s_n - s_n^old) - e_tn|^2 / noise^2  +  |L s|^2 / shape_laplacian_cm^2
        + |s|^2 / shape_scale_cm^2

(``M_tn`` the vertex's blended skinning rotation with the placement, ``e_tn`` the data residual at the old
offset, as the data term weighs it: per axis for meshes, along the normal plus a share per axis for scans;
``L`` the mesh's uniform graph Laplacian, I - D^-1 A): one sparse symmetric system of 3V unknowns per step,
solved by preconditioned conjugate gradients.  The smoothness keeps the offset from bending with the pose: a
pose error is not smooth on the mesh (it moves a band of skin against its neighbours); what is smooth, the
head turned rigidly on a constant pose error, is penalised: the best-fitting small rotation of the offset
over the head's bone region is held at zero (without it the head's orientation goes into the offset).  Only
the head's: the neck's bone regions are small and another person's offset moves each of them, which held at
zero the neck's joints would have to produce.  The larynx's displacement field stays in the offset: a wider
neck moves the same skin forward.  (Measurements: benchmarks/README.md, "Another person".)
"""
from __future__ import annotations

import numpy as np
import scipy.sparse
import scipy.sparse.linalg
import torch

from models.fit.settings import FitSettings
from models.fit.solver import Solver, State
from models.rig import HeadNeckModel


def graph_laplacian(faces: np.ndarray, count: int) -> scipy.sparse.csr_matrix:
    """The uniform graph Laplacian I - D^-1 A [V,V] of polygons [F,k] (edges around each polygon)."""
    faces = np.asarray(faces)
    rows, cols = [], []
    for k in range(faces.shape[1]):
        a, b = faces[:, k], faces[:, (k + 1) % faces.shape[1]]
        rows += [a, b]
        cols += [b, a]
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    adjacency = scipy.sparse.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(count, count)).tocsr()
    adjacency.data[:] = 1.0
    degree = np.asarray(adjacency.sum(1)).ravel()
    inverse = scipy.sparse.diags(1.0 / np.maximum(degree, 1))
    return (scipy.sparse.identity(count) - inverse @ adjacency).tocsr()


def region_rotation_rows(template: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """[3, 3V]: the linear map from an offset [3V] to the best-fitting small rotation (rotation vector; a
    translation is fitted beside it) of the region ``weights`` [V] of ``template`` [V,3], rows normalised."""
    centre = (weights[:, None] * template).sum(0) / max(weights.sum(), 1e-12)
    r = template - centre
    basis = np.zeros((len(template), 3, 6))     # offset of vertex n for unit (omega, t): omega x r + t
    basis[:, 0, 1], basis[:, 0, 2] = r[:, 2], -r[:, 1]
    basis[:, 1, 0], basis[:, 1, 2] = -r[:, 2], r[:, 0]
    basis[:, 2, 0], basis[:, 2, 1] = r[:, 1], -r[:, 0]
    basis[:, :, 3:] = np.eye(3)
    a = basis.reshape(-1, 6)
    weighted = a * np.repeat(weights, 3)[:, None]
    fit = np.linalg.solve(a.T @ weighted + 1e-9 * np.eye(6), weighted.T)[:3]   # [3, 3V]
    return fit / np.maximum(np.linalg.norm(fit, axis=1, keepdims=True), 1e-12)


class ShapeOffset:
    """``step(solver, state)``: the offset's closed-form update (module docstring)."""

    def __init__(self, model: HeadNeckModel, settings: FitSettings):
        self.settings = settings
        self.count = model.num_vertices
        laplacian = graph_laplacian(model.rig.faces, self.count)
        prior = (laplacian.T @ laplacian) / settings.shape_laplacian_cm**2
        prior = prior + scipy.sparse.identity(self.count) / settings.shape_scale_cm**2
        self.prior = scipy.sparse.kron(prior, scipy.sparse.identity(3)).tocsr()   # (vertex, axis) order
        head = model.skin_weights[:, -1].double().numpy()    # the last bone (oc1) carries the head
        self.rigid_rows = region_rotation_rows(model.template.double().numpy(), head)
        self.rigid_weight = 1e4 / settings.noise_cm**2   # far above one vertex's data weight per frame

    def energy(self, state: State) -> float:
        """The offset's prior energy (Laplacian, pull to zero, the head's rotation), in the solver's units."""
        if state.offset is None:
            return 0.0
        s = state.offset.double().numpy().reshape(-1)
        return float(s @ (self.prior @ s) + self.rigid_weight * ((self.rigid_rows @ s) ** 2).sum())

    def step(self, solver: Solver, state: State) -> State:
        settings, lin, data = self.settings, solver.lin, solver.data
        V = self.count
        A = np.zeros((V, 3, 3))
        b = np.zeros((V, 3))
        old = np.zeros((V, 3)) if state.offset is None else state.offset.double().numpy()
        inv_noise2 = 1.0 / settings.noise_cm**2
        share = settings.scan_plane_share
        for start in range(0, solver.T, settings.chunk):
            index = slice(start, min(start + settings.chunk, solver.T))
            q = lin.pose(*state.frames(index), offset=state.offset)
            vertices, weights, targets, normals = data.rows(list(range(index.start, index.stop)), q)
            rigid, _, _, _, reference = state.frames(index)
            linear = lin.blended_linear(rigid, reference, vertices).double().numpy()   # [b,n,3,3]
            qv = (q if vertices is None else q[:, vertices]).double().numpy()
            e = targets.double().numpy() - qv
            w = weights.double().numpy() * inv_noise2
            if normals is None:
                info = w[..., None, None] * np.eye(3)
            else:
                nn = normals.double().numpy()
                info = w[..., None, None] * (nn[..., :, None] * nn[..., None, :] + share * np.eye(3))
            mt_info = np.einsum("bnji,bnjk->bnik", linear, info)                    # M^T W
            block = np.einsum("bnij,bnjk->nik", mt_info, linear)                   # sum_t M^T W M
            rhs = np.einsum("bnij,bnj->ni", mt_info, e)
            index_v = np.arange(V) if vertices is None else vertices.numpy()
            A[index_v] += block
            b[index_v] += rhs + np.einsum("nij,nj->ni", block, old[index_v])
        rows = (np.arange(V)[:, None, None] * 3 + np.arange(3)[None, :, None]).repeat(3, 2)
        cols = (np.arange(V)[:, None, None] * 3 + np.arange(3)[None, None, :]).repeat(3, 1)
        data_matrix = scipy.sparse.coo_matrix((A.ravel(), (rows.ravel(), cols.ravel())), shape=(3 * V, 3 * V))
        system = (data_matrix.tocsr() + self.prior).tocsr()
        # The head's rotation is pose, not shape: penalised (rank 3), far above the data.
        rows = self.rigid_rows
        weight = self.rigid_weight
        operator = scipy.sparse.linalg.LinearOperator(
            system.shape, matvec=lambda v: system @ v + weight * (rows.T @ (rows @ v)), dtype=np.float64)
        # Conjugate gradients from the old offset, Jacobi-preconditioned (a direct factorisation of the
        # bi-Laplacian's fill-in measured 3 s a step on the built-in rig).
        preconditioner = scipy.sparse.diags(1.0 / (system.diagonal() + weight * (rows**2).sum(0)))
        offset, _ = scipy.sparse.linalg.cg(operator, b.reshape(-1), x0=old.reshape(-1), M=preconditioner,
                                           maxiter=self.settings.shape_iterations, rtol=1e-6)
        offset = offset.reshape(V, 3)
        if not np.isfinite(offset).all():
            return state
        new = state.copy()
        new.offset = torch.tensor(offset, dtype=torch.float32)
        return new
