"""The rig's forward and backward passes in vertex chunks on threads: the fast path of ``HeadNeckModel``.

Per chunk of vertices, planar ``[3,B,c]`` inside (``models.rig.skinning``): a blend GEMM (template,
expressions, shapes and correctives), the larynx at the few vertices the batch's tau range can reach, a
blended-transform GEMM, three fused multiply-adds and one write into the ``[B,N,3]`` output, all in cache.
Whole chunks are handed to ``torch.get_num_threads()`` threads (``models.rig.workers``: the caller and
helper threads, each running torch single-threaded; fewer when the batch is small), which take the next
chunk when free: there is no barrier per operation, so a thread that the OS deschedules (another job on
its core) delays only the chunk it holds.  The backward pass runs in the same chunks (each recomputed with
autograd on its thread, as activation checkpointing does); under ``torch.compile`` the chunks run out of
place on the calling thread.  The result equals ``models.rig.skinning.pose_vertices`` to float rounding.
Figures: ``benchmarks/bench_rig.py`` and ``benchmarks/README.md``.
"""
from __future__ import annotations

import math
import threading
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch.autograd.function import once_differentiable

from base.threads import single_thread
from models.rig.skinning import apply_blended, apply_dual_quaternions, blend_dual_quaternions
from models.rig.workers import run_tasks, usable_cpus

# Vertex-frames per chunk: the chunk's blended transforms (48 bytes each) stay in a core's L2 cache; at
# least 256 vertices so the per-chunk Python overhead stays small.
_CHUNK_WORK = 16384
_MIN_CHUNK = 256
# Below this many vertex-frames per thread a second thread does not pay for its hand-over (~0.1 ms).
_MIN_THREAD_WORK = 24576


def schedule(num_vertices: int, batch: int, threads: int) -> tuple[int, int]:
    """(vertices per chunk, threads) for a batch: chunks of ~``_CHUNK_WORK`` vertex-frames (at least
    ``_MIN_CHUNK`` vertices), at most one thread per ``_MIN_THREAD_WORK`` vertex-frames and per usable
    CPU, and with several threads at least 4 chunks each, so that they can balance."""
    n = num_vertices
    threads = max(1, min(threads, usable_cpus(), batch * n // _MIN_THREAD_WORK))
    size = max(_MIN_CHUNK, _CHUNK_WORK // batch)
    if threads > 1:
        size = min(size, max(_MIN_CHUNK // 4, -(-n // (4 * threads))))
    return min(size, n), threads


@dataclass(frozen=True)
class ChunkPlan:
    """The mesh cut into chunks of ``size`` vertices: per chunk (start, stop, shape_basis rows [3,K,c], skin
    weights [c,J], dqs pivots [c], skin weights [J,c]); ``starts`` the chunk starts plus the vertex count [C+1]."""

    size: int
    num_vertices: int
    chunks: list
    starts: torch.Tensor


def chunk_plan(basis: torch.Tensor, weights: torch.Tensor, pivots: torch.Tensor, size: int) -> ChunkPlan:
    """basis [K,3,N], weights [N,J], pivots [N] -> the views of each chunk of ``size`` vertices."""
    n = weights.shape[0]
    starts = list(range(0, n, size))
    chunks = [(s, min(s + size, n), Chunks.basis_rows(basis, s, s + size), weights[s: s + size],
               pivots[s: s + size], weights[s: s + size].T) for s in starts]
    return ChunkPlan(size, n, chunks, torch.tensor(starts + [n], device=pivots.device))


def larynx_reach(tau: torch.Tensor, row: torch.Tensor, rows: torch.Tensor, last_row: int) -> torch.Tensor | None:
    """Indices [A] of the larynx vertices some frame displaces, or None (all) when tau is empty or not finite.

    tau [B]; per larynx vertex its unshifted map row ``row`` [M] and the rows ``rows`` [M,2] (first, last)
    between which its map columns are non-zero; ``last_row`` = H - 1.  Exact: a vertex left out has all four
    bilinear neighbours zero in every frame of the batch (so zero value and gradient).
    """
    if not tau.numel():
        return None
    low, high = float(tau.detach().min()), float(tau.detach().max())
    if not (math.isfinite(low) and math.isfinite(high)):
        return None
    lowest = (row + low * last_row).clamp(0, last_row)
    highest = (row + high * last_row).clamp(0, last_row)
    return torch.nonzero((highest >= rows[:, 0]) & (lowest <= rows[:, 1]))[:, 0]


def pose_in_chunks(plan: ChunkPlan, skinning: str, region: torch.Tensor, threads: int, coefficients: torch.Tensor,
                   larynx: torch.Tensor, basis: torch.Tensor, weights: torch.Tensor, columns: torch.Tensor,
                   signed: torch.Tensor | None) -> torch.Tensor:
    """Posed vertices [B,N,3], differentiable in every tensor input.  Call under ``single_thread``.

    coefficients [B,K] (the last column 1, for the template), larynx [3,B,A] (L at ``region`` [A], sorted),
    basis [K,3,N], weights [N,J] (those of ``plan``), and the skinning tables: ``transform_columns`` [12B,J]
    with ``signed`` None for LBS, ``dual_quaternion_columns``' pair for DQS.
    """
    chunks = Chunks(plan, skinning, region)
    if torch.compiler.is_compiling():  # no helper threads in a traced graph: plain out-of-place chunks
        return chunks.posed(coefficients, larynx, basis, weights, columns, signed)
    return _PosedChunks.apply(chunks, threads, coefficients, larynx, basis, weights, columns, signed)


_SCRATCH = threading.local()


def _scratch(key: tuple, make):
    """Per-thread reusable buffers for the fast path, rebuilt when ``key`` (sizes, dtype, device) changes."""
    held = getattr(_SCRATCH, "held", None)
    if held is None or held[0] != key:
        with torch.inference_mode(False):  # a normal tensor: usable in and out of inference mode
            held = (key, make())
        _SCRATCH.held = held
    return held[1]


class Chunks:
    """One forward pass over vertex chunks: rest shape (blend GEMM plus the larynx), skinning, and the write
    into the output, per chunk, planar [3,B,c] inside; ``posed`` out of place (tracing), ``fill`` in place
    with per-thread buffers (the fast path), ``gradients`` per chunk by recomputation (the backward pass).

    Inputs: coefficients [B,E+S+P+1] (the last column 1, for the template), larynx [3,B,A] (L at ``region``
    [A], sorted), basis [E+S+P+1,3,N], weights [N,J], and the skinning tables (``transform_columns``, or
    ``dual_quaternion_columns``' pair; ``signed`` None for LBS).
    """

    def __init__(self, plan: ChunkPlan, skinning: str, region: torch.Tensor):
        self.skinning = skinning
        self.plan = plan.chunks
        self.size = plan.size
        self.num_vertices = plan.num_vertices
        self.region = region
        self.bounds = torch.searchsorted(region, plan.starts).tolist()  # larynx columns of chunk i: bounds[i:i+2]

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
            return apply_blended((columns @ weights.T).view(4, 3, rest.shape[1], -1), rest)
        return apply_dual_quaternions(blend_dual_quaternions(weights, self.plan[i][4], columns, signed), rest)

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

        run_tasks(task, len(self.plan), threads)
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

        run_tasks(task, len(self.plan), threads)

        def total(k: int) -> torch.Tensor | None:
            parts = [piece[k] for piece in shared if piece is not None and piece[k] is not None]
            return torch.stack(parts).sum(0) if parts else None

        return [total(0), grad_larynx, grad_basis, grad_weights, total(1), total(2)]


class _PosedChunks(torch.autograd.Function):
    """The chunked forward pass with a backward pass in chunks too (each recomputed on a thread, as
    activation checkpointing does), so neither direction runs many small multi-threaded operations."""

    @staticmethod
    def forward(ctx, chunks: Chunks, threads: int, coefficients, larynx, basis, weights, columns, signed):
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
