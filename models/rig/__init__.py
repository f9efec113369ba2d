"""The HACK head-and-neck model in torch: one pure function per step, and the module around them.

    G = LBS(T + B_S(beta) + B_E(psi) + B_P(theta) + L(eta, tau), J, theta, W)

(or DQS in place of LBS: ``skinning="dqs"``, dual-quaternion skinning, Kavan et al. 2008).

Conventions (the project's, owned here):
- Mesh in cm, y up, face towards +z; x points to the subject's left.
- theta ``[B,J,3]``: axis-angle radians per joint, the rotation of each bone in
  its own rest frame (the frame its rest transform places relative to its
  parent).  Joints run root to head: c7t1, c6c7, c5c6, c4c5, c3c4, c2c3, c1c2,
  oc1.  This is the release's layout; what each axis means anatomically is
  given by the joint's anatomical frame (below).
- psi ``[B,E]``: expression blendshape weights (E = 55, ``expression_names``).
- tau ``[B]``: vertical slide of the larynx in UV units of the larynx map,
  positive = up the neck (the map is sampled at image row ``(1 - v) + tau``).
  On the HACK template one unit is about 33 cm along the neck (0.03 ~ 1 cm).
- eta ``[B]``: larynx size; 0 = no larynx, 1 = the generic larynx (default).
- Larynx maps ``[K,H,W]``: ``L = eta * (sum_k w_k Lc_k)(u, v + tau) * ts``
  with identity weights ``w [B,K]`` (default: the first map alone), sampled
  bilinearly with ``align_corners=True`` and border padding as the release.
- "Head orientation" is ``head_rotation(theta)``: the world rotation of the
  oc1 bone relative to its rest, ``G_oc1(theta)[:3,:3] @ G_oc1(0)[:3,:3]^T``.
- Anatomical joint frames: a bone's own axes need not be anatomical (the
  release's oc1 bone points into the face, so its y axis is forward).  Each
  joint's anatomical frame (x lateral to the subject's left, y up the spine,
  z forward; so +x rotation is flexion, +y axial rotation towards the
  subject's left, +z lateral bending to the right) is its bone frame turned by the quarter-turn rotation that best
  aligns it with the world axes at rest (``anatomical_axes`` [J,3,3], the
  anatomical axes as columns in bone coordinates).  Joint limits and priors
  (``data.joint_limits``) speak anatomical frames: convert with
  ``to_anatomical(theta)`` / ``from_anatomical(theta_anatomical)``.
- Skinning: ``"lbs"`` (the release's linear blend skinning, the default) or ``"dqs"`` (dual quaternions:
  no volume loss under twist), per model (``HeadNeckModel(rig, skinning=...)``) or per call
  (``model(..., skinning=...)``).

Speed and threads: the forward pass splits the mesh into vertex chunks and works in a planar layout inside
(x, y, z planes of B frames, ``[3,B,c]``): per chunk a blend GEMM (template, expressions, shapes and
correctives), the larynx at the few vertices the batch's tau range can reach, a blended-transform GEMM, three
fused multiply-adds and one write into the ``[B,N,3]`` output, all in cache.  Whole chunks are handed to
``torch.get_num_threads()`` threads (the caller and helper threads, each running torch single-threaded; fewer
when the batch is small), which take the next chunk when free: there is no barrier per operation, so a
thread that the OS deschedules (another job on its core) delays only the chunk it holds, and on a busy
machine two threads are not slower than one.  The backward pass runs in the same chunks (each recomputed
with autograd on its thread, as activation checkpointing does); under ``torch.compile`` the chunks run on the
calling thread.  Figures: ``benchmarks/bench_rig.py`` and ``benchmarks/README.md``.
"""
from __future__ import annotations

import itertools
import os
import queue
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn
from torch.autograd.function import once_differentiable

from base.rotations import axis_angle_to_matrix, matrix_to_quaternion, quaternion_multiply
from base.threads import single_thread
from data.assets import RigData
from data.procedural_rig import build_procedural_rig

SKINNINGS = ("lbs", "dqs")

# ----------------------------------------------------------------------------- pure steps


def blend_shapes(coefficients: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """Linear blendshapes in the planar layout: ``sum_k c_bk basis_k``.

    coefficients [B,K], basis [K,3,N] (per shape its x, y and z offsets as rows) -> [B,3,N].
    ``HeadNeckModel.shape_basis`` ends with the template (coefficient 1): T + B_E + B_S + B_P in one product.
    """
    return (coefficients @ basis.reshape(basis.shape[0], -1)).reshape(coefficients.shape[0], 3, -1)


def pose_features(rotations: torch.Tensor) -> torch.Tensor:
    """SMPL-style pose-corrective features: (R - I) per joint, the root's zeroed (the release's rule).

    rotations [B,J,3,3] -> features [B,J*9].
    """
    eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
    features = rotations - eye
    features = torch.cat([torch.zeros_like(features[:, :1]), features[:, 1:]], dim=1)
    return features.reshape(rotations.shape[0], -1)


def larynx_scalar(tau: torch.Tensor, maps: torch.Tensor, map_weights: torch.Tensor,
                  grid: torch.Tensor) -> torch.Tensor:
    """Larynx displacement magnitude at vertices, the maps slid vertically by tau.

    tau [B] (UV units, + = up), maps [K,H,W], map_weights [B,K],
    grid [N,2] vertex UVs in grid_sample coordinates ((2u - 1, 2(1 - v) - 1)) -> [B,N].
    All frames sample the K maps as channels of one image (sampling is linear, so the identity
    weights apply afterwards): no per-frame copy of the maps.
    """
    shifted = grid[None].expand(tau.shape[0], -1, -1) + torch.stack([torch.zeros_like(tau), 2.0 * tau], dim=-1)[:, None]
    sampled = F.grid_sample(maps[None], shifted[None], mode="bilinear", padding_mode="border", align_corners=True)
    return torch.einsum("kbn,bk->bn", sampled[0], map_weights)


def forward_kinematics(rotations: torch.Tensor, rest_local: torch.Tensor, parents: Sequence[int]) -> torch.Tensor:
    """World transforms of the bones.  G_j = G_parent(j) @ L2P_j @ [R_j 0; 0 1].

    rotations [B,J,3,3], rest_local [J,4,4] -> [B,J,4,4].
    """
    batch, joints = rotations.shape[:2]
    local = rest_local[None].expand(batch, -1, -1, -1)
    posed_local = torch.cat([local[..., :3, :3] @ rotations, local[..., :3, 3:]], dim=-1)
    bottom = torch.zeros(batch, joints, 1, 4, dtype=rotations.dtype, device=rotations.device)
    bottom[..., 3] = 1.0
    posed_local = torch.cat([posed_local, bottom], dim=-2)
    world: list[torch.Tensor] = []
    for j, parent in enumerate(parents):
        world.append(posed_local[:, j] if parent < 0 else world[parent] @ posed_local[:, j])
    return torch.stack(world, dim=1)


def nearest_axis_permutation(rotation: torch.Tensor) -> torch.Tensor:
    """The signed permutation matrix (a proper rotation by quarter turns) nearest to ``rotation`` [3,3]."""
    remaining = rotation.abs().clone()
    out = torch.zeros_like(rotation)
    for _ in range(3):
        row, column = divmod(int(torch.argmax(remaining)), 3)
        out[row, column] = torch.sign(rotation[row, column])
        remaining[row, :] = -1.0
        remaining[:, column] = -1.0
    return out


def skinning_transforms(world: torch.Tensor, rest_world_inverse: torch.Tensor) -> torch.Tensor:
    """Per-bone transforms from rest to posed space: G_j(theta) @ G_j(0)^-1, top 3 rows.

    world [B,J,4,4], rest_world_inverse [J,4,4] -> [B,J,3,4].
    """
    return (world @ rest_world_inverse)[..., :3, :]


# Inside the forward pass vertices are planar with the batch in the middle, [3,B,M] (x, y, z planes of B
# frames of M vertices): every GEMM writes its result in that layout and every elementwise step runs over
# contiguous rows of vertices, whatever the batch size.


def _transform_columns(transforms: torch.Tensor) -> torch.Tensor:
    """[B,J,3,4] -> [12B, J], rows ordered (column k of the 3x4, row d, frame b): ``rows @ weights.T`` gives
    every vertex's blended 3x4 as [4,3,B,M]."""
    batch, joints = transforms.shape[:2]
    return transforms.permute(3, 2, 0, 1).reshape(12 * batch, joints)


def _apply_blended(blended: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """blended [4,3,B,M] (columns of per-vertex 3x4s), rest [3,B,M] -> [3,B,M]: three fused multiply-adds."""
    posed = torch.addcmul(blended[3], blended[0], rest[0:1])
    return posed.addcmul_(blended[1], rest[1:2]).addcmul_(blended[2], rest[2:3])


def linear_blend_skinning(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning, v'_n = sum_j w_nj (R_j v_n + t_j) (the release's, and smplx's ``lbs``).

    Args:
        vertices: [B,N,3] rest-pose vertices (cm).
        weights: [N,J] skinning weights (rows sum to 1).
        transforms: [B,J,3,4] rest-to-posed bone transforms (``skinning_transforms``).

    Returns:
        [B,N,3] posed vertices.  The 3x4s are blended per vertex with one [12B,J] x [J,N] product and applied
        with three fused multiply-adds (the release blends a dense 4x4 per vertex and multiplies it, ~40x
        slower).
    """
    batch = transforms.shape[0]
    blended = (_transform_columns(transforms) @ weights.T).reshape(4, 3, batch, -1)
    return _apply_blended(blended, vertices.permute(2, 0, 1)).permute(1, 2, 0)


def rigid_to_dual_quaternion(transforms: torch.Tensor) -> torch.Tensor:
    """Rigid transforms [...,3,4] ``(R | t)`` -> unit dual quaternions [...,8]: the real part ``q = quat(R)``
    (w, x, y, z; w >= 0) then the dual part ``1/2 (0, t) q`` (Hamilton product, ``base.rotations``)."""
    real = matrix_to_quaternion(transforms[..., :3, :3])
    translation = transforms[..., :3, 3]
    pure = torch.cat([torch.zeros_like(translation[..., :1]), translation], dim=-1)
    return torch.cat([real, 0.5 * quaternion_multiply(pure, real)], dim=-1)


def dual_quaternion_pivots(weights: torch.Tensor) -> torch.Tensor:
    """weights [N,J] -> [N] long: each vertex's most influential joint, the one the signs of the others'
    quaternions are aligned with before blending (Kavan et al. 2008, sec. 3.3)."""
    return weights.argmax(dim=1)


def _pivot_usage(weights: torch.Tensor, pivots: torch.Tensor) -> torch.Tensor:
    """[J,J] bool: ``usage[p, j]`` when some vertex of pivot ``p`` has a non-zero weight on joint ``j``."""
    joints = weights.shape[1]
    counts = F.one_hot(pivots, joints).to(torch.float64).T @ (weights != 0).to(torch.float64)
    return counts > 0


def _dual_quaternion_columns(dual_quaternions: torch.Tensor,
                             usage: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Per-frame dual quaternions [B,J,8] -> ``(columns [8B,J], signed [8B,J*J] or None)``, rows ordered
    (component, frame) like ``_transform_columns``.  ``signed`` holds, per pivot p (column block p), the
    quaternions with the signs that put their real parts in pivot p's hemisphere; it is None when no used
    (pivot, joint) pair needs a flip in any frame, the common case (then ``columns`` blends every vertex)."""
    batch, joints = dual_quaternions.shape[:2]
    columns = dual_quaternions.permute(2, 0, 1).reshape(8 * batch, joints)
    real = dual_quaternions[..., :4]
    flips = torch.einsum("bpc,bjc->bpj", real, real) < 0  # [B, pivot, joint]
    if not bool((flips & usage).any()):
        return columns, None
    sign = 1.0 - 2.0 * flips.to(dual_quaternions.dtype)
    signed = (sign[..., None] * dual_quaternions[:, None]).permute(3, 0, 1, 2)  # [8, B, pivot, joint]
    return columns, signed.reshape(8 * batch, joints * joints)


def _blend_dual_quaternions(weights: torch.Tensor, pivots: torch.Tensor, columns: torch.Tensor,
                            signed: torch.Tensor | None) -> torch.Tensor:
    """weights [M,J], pivots [M] -> blended dual quaternions [8,B,M] (not normalised)."""
    count, joints = weights.shape
    if signed is None:
        blended = columns @ weights.T
    else:  # each vertex's weights moved to the block of its pivot: one GEMM with the signed table
        pick = F.one_hot(pivots, joints).to(weights.dtype)
        blended = signed @ (pick[:, :, None] * weights[:, None, :]).reshape(count, joints * joints).T
    return blended.reshape(8, -1, count)


def _quadratic_forms() -> torch.Tensor:
    """[12,32]: the 3x4 ``(R | t)`` of a dual quaternion ``q_r + eps q_d`` times ``|q_r|^2``, as a linear map of
    the products ``q_r[a] q_r[b]`` (entries 0-15, a-major) and ``q_d[a] q_r[b]`` (16-31); rows ordered (column k
    of the 3x4, row d) like ``_transform_columns``.  R is the rotation of the unit quaternion, and
    t = 2 vec(q_d q_r*) = 2 (w_r d - d_w r + r x d)."""
    rr = lambda a, b: a * 4 + b  # noqa: E731 - index of q_r[a] q_r[b]
    dr = lambda a, b: 16 + a * 4 + b  # noqa: E731 - index of q_d[a] q_r[b]
    w, x, y, z = range(4)
    terms = {  # (row d, column k) -> [(coefficient, product index)]
        (0, 0): [(1, rr(w, w)), (1, rr(x, x)), (-1, rr(y, y)), (-1, rr(z, z))],
        (0, 1): [(2, rr(x, y)), (-2, rr(w, z))], (0, 2): [(2, rr(x, z)), (2, rr(w, y))],
        (1, 0): [(2, rr(x, y)), (2, rr(w, z))],
        (1, 1): [(1, rr(w, w)), (-1, rr(x, x)), (1, rr(y, y)), (-1, rr(z, z))],
        (1, 2): [(2, rr(y, z)), (-2, rr(w, x))],
        (2, 0): [(2, rr(x, z)), (-2, rr(w, y))], (2, 1): [(2, rr(y, z)), (2, rr(w, x))],
        (2, 2): [(1, rr(w, w)), (-1, rr(x, x)), (-1, rr(y, y)), (1, rr(z, z))],
        (0, 3): [(2, dr(x, w)), (-2, dr(w, x)), (2, dr(z, y)), (-2, dr(y, z))],
        (1, 3): [(2, dr(y, w)), (-2, dr(w, y)), (2, dr(x, z)), (-2, dr(z, x))],
        (2, 3): [(2, dr(z, w)), (-2, dr(w, z)), (2, dr(y, x)), (-2, dr(x, y))],
    }
    forms = torch.zeros(12, 32, dtype=torch.float64)
    for (d, k), entries in terms.items():
        for coefficient, index in entries:
            forms[3 * k + d, index] += coefficient
    return forms


_QUADRATIC_FORMS = _quadratic_forms()


def _apply_dual_quaternions(blended: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """blended [8,B,M] (real w,x,y,z | dual w,x,y,z, not normalised), rest [3,B,M] -> [3,B,M].

    The rigid transform of the normalised dual quaternion, ``(R | t) = Q(q_r, q_d) / |q_r|^2`` with Q the
    quadratic forms of ``_quadratic_forms`` (the products of the components, then one small GEMM), applied
    like LBS's blended 3x4s.
    """
    real = blended[:4]
    products = (blended[:, None] * real[None]).reshape(32, -1)  # q[a] q_r[b], a-major
    forms = _QUADRATIC_FORMS.to(dtype=blended.dtype, device=blended.device)
    transform = (forms @ products).view(4, 3, *blended.shape[1:])
    return _apply_blended(transform, rest) / (real * real).sum(0).clamp_min(torch.finfo(blended.dtype).tiny)


def dual_quaternion_skinning(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor,
                             pivots: torch.Tensor | None = None) -> torch.Tensor:
    """Dual-quaternion linear blending (Kavan, Collins, Zara and O'Sullivan, "Geometric skinning with
    approximate dual quaternion blending", ACM TOG 27(4), 2008), a drop-in for ``linear_blend_skinning``.

    v'_n = T(q_n) v_n with q_n = sum_j w_nj s_nj Q_j normalised by its real part's norm, Q_j the unit dual
    quaternion of bone j's rigid transform and s_nj = +-1 putting Q_j's real part in the hemisphere of the
    pivot's (``dual_quaternion_pivots``).  A twisted chain keeps its volume and girth where LBS collapses it;
    with one-hot weights it equals LBS.

    Args:
        vertices: [B,N,3] rest-pose vertices (cm).
        weights: [N,J] skinning weights (rows sum to 1).
        transforms: [B,J,3,4] rigid rest-to-posed bone transforms (``skinning_transforms``).
        pivots: [N] long, each vertex's sign-reference joint; default the joint of its largest weight.

    Returns:
        [B,N,3] posed vertices.
    """
    pivots = dual_quaternion_pivots(weights) if pivots is None else pivots
    columns, signed = _dual_quaternion_columns(rigid_to_dual_quaternion(transforms), _pivot_usage(weights, pivots))
    blended = _blend_dual_quaternions(weights, pivots, columns, signed)
    return _apply_dual_quaternions(blended, vertices.permute(2, 0, 1)).permute(1, 2, 0)


# ----------------------------------------------------------------------------- threads

# Vertex-frames per chunk: the chunk's blended transforms (48 bytes each) stay in a core's L2 cache; at
# least 256 vertices so the per-chunk Python overhead stays small (measured in benchmarks/bench_rig.py).
_CHUNK_WORK = 16384
_MIN_CHUNK = 256
# Below this many vertex-frames per thread a second thread does not pay for its hand-over (~0.1 ms).
_MIN_THREAD_WORK = 24576


def _usable_cpus() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class _ChunkWorkers:
    """Helper threads that run whole chunks of a forward pass beside the caller.

    Each helper runs torch single-threaded (``torch.set_num_threads(1)`` is per thread for OpenMP and
    MKL); a call hands out chunk indices from a shared counter, so the threads balance themselves and
    none waits for another except at the end of the call.  Created on first use; a forked child starts
    without them and makes its own.
    """

    def __init__(self):
        self._reset()
        os.register_at_fork(after_in_child=self._reset)

    def _reset(self) -> None:
        self._threads: list[threading.Thread] = []
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()

    def _grow(self, count: int) -> None:
        with self._lock:
            while len(self._threads) < count:
                ready = threading.Event()
                thread = threading.Thread(target=self._serve, args=(self._jobs, ready), daemon=True,
                                          name=f"hackneck-rig-{len(self._threads)}")
                thread.start()
                ready.wait()
                self._threads.append(thread)

    @staticmethod
    def _serve(jobs: queue.SimpleQueue, ready: threading.Event) -> None:
        torch.set_num_threads(1)  # also sets torch's default for new threads: the caller restores it
        ready.set()
        while True:
            jobs.get()()

    def run(self, task, count: int, threads: int) -> None:
        """``task(i)`` for every i < count on the calling thread and ``threads - 1`` helpers; the first
        exception is re-raised here.  Call under ``single_thread``."""
        helpers = min(threads, count) - 1
        if helpers <= 0:
            for i in range(count):
                task(i)
            return
        self._grow(helpers)
        indices = itertools.count()
        failures: list[BaseException] = []
        done = threading.Semaphore(0)
        inference = torch.is_inference_mode_enabled()

        def drain() -> None:
            while not failures:
                i = next(indices)
                if i >= count:
                    return
                try:
                    task(i)
                except BaseException as error:  # noqa: B036 - handed to the caller
                    failures.append(error)

        def helper() -> None:
            try:
                with torch.inference_mode(inference), torch.no_grad():
                    drain()
            finally:
                done.release()

        for _ in range(helpers):
            self._jobs.put(helper)
        drain()
        for _ in range(helpers):
            done.acquire()
        if failures:
            raise failures[0]


_WORKERS = _ChunkWorkers()
_SCRATCH = threading.local()


def _scratch(key: tuple, make):
    """Per-thread reusable buffers for the fast path, rebuilt when ``key`` (sizes, dtype, device) changes."""
    held = getattr(_SCRATCH, "held", None)
    if held is None or held[0] != key:
        with torch.inference_mode(False):  # a normal tensor: usable in and out of inference mode
            held = (key, make())
        _SCRATCH.held = held
    return held[1]


class _Chunks:
    """One forward pass over vertex chunks: rest shape (blend GEMM plus the larynx), skinning, and the write
    into the output, per chunk, planar [3,B,c] inside; ``posed`` out of place (tracing), ``fill`` in place
    with per-thread buffers (the fast path), ``gradients`` per chunk by recomputation (the backward pass).

    Inputs: coefficients [B,E+S+P+1] (the last column 1, for the template), larynx [3,B,A] (L at ``region``
    [A], sorted), basis [E+S+P+1,3,N], weights [N,J], and the skinning tables (``_transform_columns``, or
    ``_dual_quaternion_columns``' pair; ``signed`` None for LBS).
    """

    def __init__(self, model: HeadNeckModel, skinning: str, size: int, region: torch.Tensor):
        self.skinning = skinning
        self.plan, starts = model._plan(size)
        self.size = size
        self.num_vertices = model.num_vertices
        self.region = region
        self.bounds = torch.searchsorted(region, starts).tolist()  # larynx columns of chunk i: bounds[i:i+2]

    def rest(self, i: int, coefficients, larynx, basis, out: torch.Tensor | None = None) -> torch.Tensor:
        """[3,B,c] rest shape of chunk i; ``basis`` [3,K,c] its rows, ``larynx`` [3,B,a] its larynx columns."""
        rest = torch.matmul(coefficients, basis, out=out)
        if larynx is not None:
            low, high = self.bounds[i], self.bounds[i + 1]
            rest = rest.index_add_(2, self.region[low:high] - self.plan[i][0], larynx)
        return rest

    def skin(self, i: int, rest: torch.Tensor, weights: torch.Tensor, columns: torch.Tensor,
             signed: torch.Tensor | None) -> torch.Tensor:
        if self.skinning == "lbs":
            return _apply_blended((columns @ weights.T).view(4, 3, rest.shape[1], -1), rest)
        return _apply_dual_quaternions(_blend_dual_quaternions(weights, self.plan[i][4], columns, signed), rest)

    def larynx_columns(self, i: int, larynx: torch.Tensor) -> torch.Tensor | None:
        low, high = self.bounds[i], self.bounds[i + 1]
        return larynx[:, :, low:high] if high > low else None

    @staticmethod
    def basis_rows(basis: torch.Tensor, start: int, stop: int) -> torch.Tensor:
        """[K,3,N] -> the chunk's [3,K,c] (a view, for a batched product per coordinate)."""
        return basis[:, :, start:stop].transpose(0, 1)

    def posed(self, coefficients, larynx, basis, weights, columns, signed) -> torch.Tensor:
        """[B,N,3], out of place."""
        pieces = []
        for i, (start, stop) in enumerate(p[:2] for p in self.plan):
            rest = self.rest(i, coefficients, self.larynx_columns(i, larynx), self.basis_rows(basis, start, stop))
            pieces.append(self.skin(i, rest, weights[start:stop], columns, signed).permute(1, 2, 0))
        return torch.cat(pieces, dim=1)

    def fill(self, threads: int, coefficients, larynx, columns, signed) -> torch.Tensor:
        """[B,N,3] on ``threads`` threads (no autograd), with the model's own basis and weights."""
        batch = coefficients.shape[0]
        dtype, device = coefficients.dtype, coefficients.device
        posed = torch.empty(batch, self.num_vertices, 3, dtype=dtype, device=device)
        size = self.size

        def views(count: int) -> tuple:
            """This thread's buffers as rest [3,B,c] and its rows, blended [12B,c] and its four [3,B,c]
            columns, chunk [3,B,c]; made once per thread and chunk size (fewer calls holding the GIL)."""
            flat = _scratch((size, batch, dtype, device),
                            lambda: torch.empty(18 * size * batch, dtype=dtype, device=device))
            held = getattr(_SCRATCH, "views", None)
            if held is None or held[0] is not flat or held[1] != count:
                rest = flat[: 3 * batch * count].view(3, batch, count)
                blended = flat[3 * batch * count: 15 * batch * count].view(12 * batch, count)
                chunk = flat[15 * batch * count: 18 * batch * count].view(3, batch, count)
                held = (flat, count, (rest, rest[0:1], rest[1:2], rest[2:3], blended,
                                      *blended.view(4, 3, batch, count), chunk))
                _SCRATCH.views = held
            return held[2]

        def task(i: int) -> None:
            start, stop, basis, weights, _, weights_by_joint = self.plan[i]
            rest, x, y, z, blended, b0, b1, b2, b3, chunk = views(stop - start)
            self.rest(i, coefficients, self.larynx_columns(i, larynx), basis, out=rest)
            if self.skinning == "lbs":
                torch.mm(columns, weights_by_joint, out=blended)
                torch.addcmul(b3, b0, x, out=chunk).addcmul_(b1, y).addcmul_(b2, z)
            else:
                chunk = self.skin(i, rest, weights, columns, signed)
            posed[:, start:stop].copy_(chunk.permute(1, 2, 0))  # while the chunk is in cache

        _WORKERS.run(task, len(self.plan), threads)
        return posed

    def gradients(self, threads: int, grad: torch.Tensor, needs: Sequence[bool], coefficients, larynx, basis,
                  weights, columns, signed) -> list[torch.Tensor | None]:
        """Gradients of (coefficients, larynx, basis, weights, columns, signed) where ``needs`` says, for
        the output gradient ``grad`` [B,N,3]: each chunk recomputed with autograd on its own thread, the
        pieces of the shared inputs summed in chunk order (deterministic whatever thread ran which)."""
        inputs = (coefficients, larynx, basis, weights, columns, signed)
        shared = [None] * len(self.plan)  # per chunk: gradients of coefficients, columns, signed
        grad_larynx = torch.zeros_like(larynx) if needs[1] else None
        grad_basis = torch.zeros_like(basis) if needs[2] else None
        grad_weights = torch.zeros_like(weights) if needs[3] else None

        def task(i: int) -> None:
            start, stop = self.plan[i][:2]
            leaf = [None if x is None else x.detach().requires_grad_(bool(need))
                    for x, need in zip(inputs, needs, strict=True)]
            with torch.enable_grad():
                pieces = (leaf[0], self.larynx_columns(i, leaf[1]), self.basis_rows(leaf[2], start, stop),
                          leaf[3][start:stop], leaf[4], leaf[5])
                posed = self.skin(i, self.rest(i, *pieces[:3]), *pieces[3:])
                wanted = [k for k, x in enumerate(pieces) if x is not None and needs[k]]
                if not wanted:
                    return
                found = torch.autograd.grad(posed, [pieces[k] for k in wanted],
                                            grad[:, start:stop].permute(2, 0, 1), allow_unused=True)
            result = dict(zip(wanted, found, strict=True))
            if result.get(1) is not None:
                grad_larynx[:, :, self.bounds[i]: self.bounds[i + 1]] = result[1]
            if result.get(2) is not None:
                grad_basis[:, :, start:stop] = result[2].transpose(0, 1)
            if result.get(3) is not None:
                grad_weights[start:stop] = result[3]
            shared[i] = (result.get(0), result.get(4), result.get(5))

        _WORKERS.run(task, len(self.plan), threads)

        def total(k: int) -> torch.Tensor | None:
            parts = [piece[k] for piece in shared if piece is not None and piece[k] is not None]
            return torch.stack(parts).sum(0) if parts else None

        return [total(0), grad_larynx, grad_basis, grad_weights, total(1), total(2)]


class _PosedChunks(torch.autograd.Function):
    """The chunked forward pass with a backward pass in chunks too (each recomputed on a thread, as
    activation checkpointing does), so neither direction runs many small multi-threaded operations."""

    @staticmethod
    def forward(ctx, chunks: _Chunks, threads: int, coefficients, larynx, basis, weights, columns, signed):
        ctx.chunks, ctx.threads = chunks, threads
        ctx.save_for_backward(coefficients, larynx, basis, weights, columns, signed)
        return chunks.fill(threads, coefficients, larynx, columns, signed)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad):
        needs = ctx.needs_input_grad[2:]
        with single_thread():
            found = ctx.chunks.gradients(ctx.threads, grad, needs, *ctx.saved_tensors)
        return (None, None, *found)


# ----------------------------------------------------------------------------- module


class HeadNeckModel(nn.Module):
    """A HACK-style head-and-neck rig (the real release via ``load``, the procedural one via ``builtin``).

    Call: ``model(theta [B,J,3], psi [B,E]=None, tau [B]=None, eta [B]=None,
    beta [B,S]=None, larynx_weights [B,K]=None, skinning=None) -> vertices [B,N,3]`` (cm).
    Missing inputs take their rest value (zero; eta = 1; the first larynx map); ``skinning`` is
    ``"lbs"`` or ``"dqs"`` (default: the model's ``skinning`` attribute, ``"lbs"`` unless given).
    """

    def __init__(self, rig: RigData, skinning: str = "lbs"):
        super().__init__()
        self.rig = rig
        self.skinning = _skinning_name(skinning)
        dtype = torch.float32
        self.joint_names: list[str] = [str(n) for n in rig.joint_names]
        self.expression_names: list[str] = [str(n) for n in rig.expression_names]
        self.parents: list[int] = [int(p) for p in rig.parents]
        self.faces = torch.tensor(rig.faces.astype(np.int64))
        n = len(rig.template)
        self.register_buffer("template", torch.tensor(rig.template, dtype=dtype))
        self.register_buffer("skin_weights", torch.tensor(rig.skin_weights, dtype=dtype))
        # One planar basis [E + S + P + 1, 3, N] (per shape the x, y and z offsets of all vertices as rows) for
        # expressions, identity shapes, pose correctives and the template: T + B_E(psi) + B_S(beta) + B_P(theta)
        # is a single product with (psi, beta, pose features, 1).
        bases = [rig.expression_deltas, rig.shape_deltas, rig.pose_correctives.reshape(-1, n, 3),
                 rig.template.reshape(1, n, 3)]
        self.num_expressions, self.num_shapes, self.num_pose_features = (len(b) for b in bases[:3])
        basis = np.concatenate([np.asarray(b, np.float64).reshape(-1, n, 3) for b in bases]).transpose(0, 2, 1)
        self.register_buffer("shape_basis", torch.tensor(np.ascontiguousarray(basis), dtype=dtype))
        self.register_buffer("rest_local", torch.tensor(rig.joint_rest_local, dtype=dtype))
        rest_world = forward_kinematics(torch.eye(3, dtype=torch.float64).expand(1, len(self.parents), 3, 3),
                                        torch.tensor(rig.joint_rest_local, dtype=torch.float64), self.parents)[0]
        self.register_buffer("rest_world", rest_world.to(dtype))
        self.register_buffer("rest_world_inverse", torch.linalg.inv(rest_world).to(dtype))
        # Columns: world x, y, z in each bone's coordinates, snapped to the nearest quarter turns.
        axes = torch.stack([nearest_axis_permutation(r[:3, :3].T) for r in rest_world])
        self.register_buffer("anatomical_axes", axes.to(dtype))
        self.register_buffer("larynx_maps", torch.tensor(rig.larynx_maps, dtype=dtype))
        self.register_buffer("larynx_direction", torch.tensor(rig.larynx_direction, dtype=dtype))
        self._init_larynx_region(rig)
        pivots = dual_quaternion_pivots(self.skin_weights)
        self.register_buffer("dqs_pivots", pivots)
        self.register_buffer("dqs_usage", _pivot_usage(self.skin_weights, pivots))
        self._plans: dict = {}

    def _init_larynx_region(self, rig: RigData) -> None:
        """``larynx_vertices`` [M]: the vertices whose map columns (or bilinear neighbours) hold a non-zero
        value, the only ones L can move as tau slides along v; ``larynx_grid`` [M,2] their sampling points;
        per vertex the unshifted sampling row ``larynx_row`` and the rows ``larynx_rows`` [M,2] (first,
        last; widened by 2 rows for rounding) between which its columns are non-zero: a frame displaces the
        vertex only if its shifted row falls between them (``_larynx_active``)."""
        uv = torch.tensor(rig.vertex_uv, dtype=torch.float64)
        grid = torch.stack([2 * uv[:, 0] - 1, 2 * (1 - uv[:, 1]) - 1], dim=-1)
        _, height, width = rig.larynx_maps.shape
        column = np.floor((grid[:, 0].clamp(-1, 1).numpy() + 1) / 2 * (width - 1)).astype(int)
        columns = np.stack([np.clip(column, 0, width - 1), np.clip(column + 1, 0, width - 1)])  # [2, N]
        occupied = np.abs(rig.larynx_maps).max(axis=0) > 0  # [H, W]
        vertices = np.flatnonzero(occupied[:, columns].any(axis=(0, 1)))
        self.register_buffer("larynx_vertices", torch.tensor(vertices))
        self.register_buffer("larynx_grid", grid[vertices].to(torch.float32))
        rows = occupied[:, columns[:, vertices]].any(axis=1)  # [H, M]
        index = np.arange(height)[:, None]
        first = np.where(rows, index, height).min(axis=0) - 2.0
        last = np.where(rows, index, -1).max(axis=0) + 2.0
        row = (self.larynx_grid[:, 1].double() + 1) / 2 * (height - 1)
        self.register_buffer("larynx_row", row.to(torch.float32))
        self.register_buffer("larynx_rows", torch.tensor(np.stack([first, last], axis=1), dtype=torch.float32))

    # ------------------------------------------------------------------ constructors

    @classmethod
    def load(cls, path: str | os.PathLike, skinning: str = "lbs") -> HeadNeckModel:
        """A rig file written by ``python -m data.assets`` (the real HACK release)."""
        return cls(RigData.load(path), skinning=skinning)

    @classmethod
    def builtin(cls, skinning: str = "lbs") -> HeadNeckModel:
        """The built-in procedural rig (no download)."""
        return cls(build_procedural_rig(), skinning=skinning)

    @classmethod
    def from_config(cls, path: str | os.PathLike | None, skinning: str = "lbs") -> HeadNeckModel:
        """``path`` to a rig file, or None / "" / "builtin" for the procedural rig."""
        if path in (None, "", "builtin"):
            return cls.builtin(skinning=skinning)
        return cls.load(Path(path), skinning=skinning)

    # ------------------------------------------------------------------ sizes

    @property
    def num_vertices(self) -> int:
        return self.template.shape[0]

    @property
    def num_joints(self) -> int:
        return len(self.parents)

    @property
    def num_larynx_maps(self) -> int:
        return self.larynx_maps.shape[0]

    # ------------------------------------------------------------------ kinematics

    def rotations(self, theta: torch.Tensor) -> torch.Tensor:
        """theta [B,J,3] -> [B,J,3,3]."""
        self._check(theta, (self.num_joints, 3), "theta")
        return axis_angle_to_matrix(theta.to(self.template.dtype))

    def joint_transforms(self, theta: torch.Tensor) -> torch.Tensor:
        """World transforms of the bones (bone frame -> world) [B,J,4,4] for theta [B,J,3]."""
        return forward_kinematics(self.rotations(theta), self.rest_local, self.parents)

    def head_rotation(self, theta: torch.Tensor) -> torch.Tensor:
        """Head orientation [B,3,3]: oc1's world rotation relative to rest."""
        world = self.joint_transforms(theta)
        return world[:, -1, :3, :3] @ self.rest_world[-1, :3, :3].T

    def to_anatomical(self, theta: torch.Tensor) -> torch.Tensor:
        """theta [...,J,3] in bone frames -> the same rotations in anatomical joint frames."""
        return torch.einsum("jab,...ja->...jb", self.anatomical_axes.to(theta), theta)

    def from_anatomical(self, theta: torch.Tensor) -> torch.Tensor:
        """theta [...,J,3] in anatomical joint frames -> bone frames (the model's input)."""
        return torch.einsum("jab,...jb->...ja", self.anatomical_axes.to(theta), theta)

    @property
    def anatomical_rest_rotations(self) -> torch.Tensor:
        """[J,3,3] rest world rotations of the anatomical joint frames (bone rest rotation @ axes)."""
        return self.rest_world[:, :3, :3] @ self.anatomical_axes

    # ------------------------------------------------------------------ geometry

    def larynx_region_offsets(self, tau: torch.Tensor, eta: torch.Tensor,
                              larynx_weights: torch.Tensor | None = None) -> torch.Tensor:
        """L(eta, tau) [B,M,3] at ``larynx_vertices`` [M], the only vertices it can move."""
        tau, eta, larynx_weights = self._larynx_arguments(tau, eta, larynx_weights)
        scalar = larynx_scalar(tau, self.larynx_maps, larynx_weights, self.larynx_grid)
        return (eta[:, None] * scalar)[..., None] * self.larynx_direction

    def larynx_offsets(self, tau: torch.Tensor, eta: torch.Tensor,
                       larynx_weights: torch.Tensor | None = None) -> torch.Tensor:
        """L(eta, tau) at every vertex [B,N,3] (zero outside ``larynx_vertices``)."""
        out = self.template.new_zeros(tau.shape[0], self.num_vertices, 3)
        return out.index_add(1, self.larynx_vertices, self.larynx_region_offsets(tau, eta, larynx_weights))

    @property
    def expression_deltas(self) -> torch.Tensor:
        """[E,N,3] expression blendshape offsets (cm), a view of ``shape_basis``."""
        return self.shape_basis[: self.num_expressions].transpose(1, 2)

    def blend_coefficients(self, batch: int, psi=None, beta=None, rotations=None) -> torch.Tensor:
        """[B, E+S+P]: psi, beta and pose-corrective features, zero where not given."""
        parts = []
        for value, size, name in ((psi, self.num_expressions, "psi"), (beta, self.num_shapes, "beta")):
            if value is None:
                parts.append(self.template.new_zeros(batch, size))
            else:
                self._check(value, (size,), name, batch)
                parts.append(value.to(self.template.dtype))
        if self.num_pose_features:
            parts.append(pose_features(rotations) if rotations is not None
                         else self.template.new_zeros(batch, self.num_pose_features))
        return torch.cat(parts, dim=1)

    def rest_shape(self, psi=None, tau=None, eta=None, beta=None, larynx_weights=None,
                   rotations: torch.Tensor | None = None) -> torch.Tensor:
        """The unposed shape T + B_S + B_E + B_P + L, [B,N,3]: psi [B,E], tau [B], eta [B], beta [B,S],
        larynx_weights [B,K], rotations [B,J,3,3] (for the pose correctives), each optional; B is the
        inputs' batch (1 when none is given)."""
        given = [x for x in (psi, tau, eta, beta, larynx_weights, rotations) if x is not None]
        batch = given[0].shape[0] if given else 1
        coefficients = self.blend_coefficients(batch, psi, beta, rotations)
        coefficients = torch.cat([coefficients, coefficients.new_ones(batch, 1)], dim=1)
        shape = blend_shapes(coefficients, self.shape_basis).transpose(1, 2)
        tau, eta = self._larynx_inputs(batch, tau, eta)
        return shape.index_add(1, self.larynx_vertices, self.larynx_region_offsets(tau, eta, larynx_weights))

    def forward(self, theta: torch.Tensor, psi: torch.Tensor | None = None, tau: torch.Tensor | None = None,
                eta: torch.Tensor | None = None, beta: torch.Tensor | None = None,
                larynx_weights: torch.Tensor | None = None, skinning: str | None = None) -> torch.Tensor:
        """Posed vertices [B,N,3] (cm).

        Args:
            theta: [B,J,3] axis-angle per joint in its bone frame.
            psi: [B,E] expression weights; beta [B,S] identity shape; tau [B], eta [B] the larynx;
                larynx_weights [B,K] identity weights of the larynx maps (each optional, see the class).
            skinning: "lbs" or "dqs"; None takes the model's ``skinning``.

        Returns:
            [B,N,3] vertices; differentiable in every input.  Speed: see the module docstring (threads).
        """
        skinning = _skinning_name(self.skinning if skinning is None else skinning)
        threads = torch.get_num_threads()
        with single_thread():
            return self._pose(theta, psi, tau, eta, beta, larynx_weights, skinning, threads)

    # ------------------------------------------------------------------ the forward pass

    def _pose(self, theta, psi, tau, eta, beta, larynx_weights, skinning: str, threads: int) -> torch.Tensor:
        rotations = self.rotations(theta)
        batch = theta.shape[0]
        coefficients = self.blend_coefficients(batch, psi, beta, rotations)
        tau, eta = self._larynx_inputs(batch, tau, eta)
        if batch == 0:
            return self.template.new_zeros(0, self.num_vertices, 3)
        # [B, E+S+P+1]: the last column multiplies the template, the last shape of ``shape_basis``.
        coefficients = torch.cat([coefficients, coefficients.new_ones(batch, 1)], dim=1)
        region, larynx = self._larynx_active(tau, eta, larynx_weights)  # [A], [3,B,A]
        transforms = skinning_transforms(forward_kinematics(rotations, self.rest_local, self.parents),
                                         self.rest_world_inverse)
        if skinning == "lbs":
            tables = (_transform_columns(transforms), None)
        else:
            tables = _dual_quaternion_columns(rigid_to_dual_quaternion(transforms), self.dqs_usage)
        if torch.compiler.is_compiling():  # no helper threads in a traced graph: plain out-of-place chunks
            chunks = _Chunks(self, skinning, self._schedule(batch, 1)[0], region)
            return chunks.posed(coefficients, larynx, self.shape_basis, self.skin_weights, *tables)
        size, threads = self._schedule(batch, threads)
        return _PosedChunks.apply(_Chunks(self, skinning, size, region), threads, coefficients, larynx,
                                  self.shape_basis, self.skin_weights, *tables)

    def _schedule(self, batch: int, threads: int) -> tuple[int, int]:
        """(vertices per chunk, threads) for a batch: chunks of ~``_CHUNK_WORK`` vertex-frames (at least
        ``_MIN_CHUNK`` vertices), at most one thread per ``_MIN_THREAD_WORK`` vertex-frames and per usable
        CPU, and with several threads at least 4 chunks each, so that they can balance."""
        n = self.num_vertices
        threads = max(1, min(threads, _usable_cpus(), batch * n // _MIN_THREAD_WORK))
        size = max(_MIN_CHUNK, _CHUNK_WORK // batch)
        if threads > 1:
            size = min(size, max(_MIN_CHUNK // 4, -(-n // (4 * threads))))
        return min(size, n), threads

    def _plan(self, size: int) -> tuple[list, torch.Tensor]:
        """Vertex chunks of ``size``: (start, stop, shape_basis rows [3,K,c], skin weights [c,J], dqs pivots
        [c], skin weights [J,c]) each, and the chunk starts plus the vertex count [C+1] (cached per size; ``.to()``,
        ``.double()`` clear it)."""
        if size not in self._plans:
            n = self.num_vertices
            starts = list(range(0, n, size))
            plan = [(s, min(s + size, n), _Chunks.basis_rows(self.shape_basis, s, s + size),
                     self.skin_weights[s: s + size], self.dqs_pivots[s: s + size],
                     self.skin_weights[s: s + size].T) for s in starts]
            self._plans[size] = (plan, torch.tensor(starts + [n], device=self.larynx_vertices.device))
        return self._plans[size]

    def _apply(self, fn, *args, **kwargs):
        self._plans = {}
        return super()._apply(fn, *args, **kwargs)

    def _larynx_active(self, tau: torch.Tensor, eta: torch.Tensor,
                       larynx_weights: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The larynx vertices some frame of the batch displaces (sorted) [A], and L there [3,B,A].

        Exact: a vertex outside it has all four bilinear neighbours zero in every frame (so zero value and
        gradient), from the batch's tau range and the vertex's non-zero rows (``_init_larynx_region``)."""
        tau, eta, larynx_weights = self._larynx_arguments(tau, eta, larynx_weights)
        keep = None
        if tau.numel():
            low, high = float(tau.detach().min()), float(tau.detach().max())
            if np.isfinite(low) and np.isfinite(high):
                last_row = self.larynx_maps.shape[1] - 1
                lowest = (self.larynx_row + low * last_row).clamp(0, last_row)
                highest = (self.larynx_row + high * last_row).clamp(0, last_row)
                keep = torch.nonzero((highest >= self.larynx_rows[:, 0]) & (lowest <= self.larynx_rows[:, 1]))[:, 0]
        region = self.larynx_vertices if keep is None else self.larynx_vertices[keep]
        grid = self.larynx_grid if keep is None else self.larynx_grid[keep]
        scalar = larynx_scalar(tau, self.larynx_maps, larynx_weights, grid)  # [B, A]
        return region, (eta[:, None] * scalar)[None] * self.larynx_direction[:, None, None]

    # ------------------------------------------------------------------ helpers

    def _larynx_arguments(self, tau, eta, larynx_weights) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        batch = tau.shape[0]
        self._check(tau, (), "tau", batch)
        self._check(eta, (), "eta", batch)
        tau, eta = tau.to(self.template.dtype), eta.to(self.template.dtype)
        if larynx_weights is None:
            larynx_weights = tau.new_zeros(batch, self.num_larynx_maps)
            larynx_weights[:, 0] = 1.0
        self._check(larynx_weights, (self.num_larynx_maps,), "larynx_weights", batch)
        return tau, eta, larynx_weights.to(self.template.dtype)

    def _larynx_inputs(self, batch: int, tau, eta) -> tuple[torch.Tensor, torch.Tensor]:
        tau = self.template.new_zeros(batch) if tau is None else tau
        eta = self.template.new_ones(batch) if eta is None else eta
        self._check(tau, (), "tau", batch)
        self._check(eta, (), "eta", batch)
        return tau, eta

    @staticmethod
    def _check(value: torch.Tensor, trailing: tuple[int, ...], name: str, batch: int | None = None) -> None:
        if tuple(value.shape[1:]) != trailing or (batch is not None and value.shape[0] != batch):
            expected = f"[{batch if batch is not None else 'B'}" + "".join(f",{d}" for d in trailing) + "]"
            raise ValueError(f"{name} has shape {list(value.shape)}, expected {expected}")

    def neutral(self, batch: int = 1) -> torch.Tensor:
        """The rest pose theta = 0 [B,J,3]."""
        return self.template.new_zeros(batch, self.num_joints, 3)


def _skinning_name(skinning: str) -> str:
    if skinning not in SKINNINGS:
        raise ValueError(f"skinning={skinning!r}: expected one of {', '.join(SKINNINGS)}")
    return skinning
