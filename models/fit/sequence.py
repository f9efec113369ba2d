"""One sequence's fit, whatever the capture: the initial placement, the coarse-to-fine stages, the result.

``fit_sequence`` takes a data term (``models.fit.meshes`` / ``models.fit.scans``) and the per-frame initial
placements, runs ``models.fit.solver.Solver``'s stages (placement; + theta; + psi, tau, eta and the shape
offset) and assembles the ``FitResult`` with the per-joint uncertainty from the last Gauss-Newton Hessian.
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable

import numpy as np
import torch

from base.rotations import matrix_to_axis_angle
from models.fit.linearise import RigLinearisation
from models.fit.settings import FitResult, FitSettings
from models.fit.solver import Solver, State, placement_of
from models.rig import HeadNeckModel


def kabsch(source: torch.Tensor, target: torch.Tensor, weights: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Weighted rigid fit target ~ R source + t: source [n,3], target [B,n,3], weights [n] -> R [B,3,3], t [B,3]."""
    w = weights / weights.sum()
    mu_s = (w[:, None] * source).sum(0)
    mu_t = (w[None, :, None] * target).sum(1)
    cov = torch.einsum("n,bni,nj->bij", w, target - mu_t[:, None], source - mu_s)
    u, _, vt = torch.linalg.svd(cov.double())
    d = torch.sign(torch.linalg.det(u @ vt))
    fix = torch.diag_embed(torch.stack([torch.ones_like(d), torch.ones_like(d), d], -1))
    rotation = (u @ fix @ vt).float()
    return rotation, mu_t - (rotation @ mu_s[:, None])[..., 0]


def mean_rotation(rotations: torch.Tensor) -> torch.Tensor:
    """The chordal mean of rotations [T,3,3] -> [3,3]."""
    u, _, vt = torch.linalg.svd(rotations.double().mean(0))
    d = torch.sign(torch.linalg.det(u @ vt))
    return (u @ torch.diag(torch.stack([torch.ones_like(d), torch.ones_like(d), d])) @ vt).float()


def initial_state(model: HeadNeckModel, rotation: torch.Tensor, translation: torch.Tensor) -> State:
    """The rest pose placed per frame by rotation [T,3,3] and translation [T,3]."""
    T = len(rotation)
    reference = mean_rotation(rotation)
    r = matrix_to_axis_angle(rotation @ reference.T)
    rigid = torch.cat([r, translation, torch.zeros(T, 3 * (model.num_joints - 1))], 1).float()
    return State(rigid, torch.zeros(T, model.num_expressions), torch.zeros(T), torch.ones(1), reference)


def fit_sequence(model: HeadNeckModel, data, state: State, settings: FitSettings,
                 progress: Callable[[int], None] | None = None, shape=None) -> FitResult:
    """The coarse-to-fine stages from ``state``; ``shape`` (``models.fit.shape.ShapeOffset``, or None) updates
    the offset after each step of the last stage."""
    started = time.perf_counter()
    lin = RigLinearisation(model)
    T = len(state.rigid)
    solver = Solver(lin, settings, data, T, progress)
    if shape is not None:
        solver.extra_energy = shape.energy
    lay = lin.layout
    placement, neck, everything = (np.zeros(lay.size, bool) for _ in range(3))
    placement[lay.rotation] = placement[lay.translation] = True
    neck[lay.rigid] = True
    everything[:] = True
    iterations = settings.iterations
    solver._passes_total = sum(iterations) + 1
    # Geman-McClure's scale falls geometrically from robust_start_cm to robust_scale_cm, one value per stage
    # (constant within a stage, so that Levenberg-Marquardt can compare the energies of its steps).
    levels = [settings.robust_start_cm * (settings.robust_scale_cm / settings.robust_start_cm) ** (k / 2)
              for k in range(3)]
    # Meshes: the placement and neck stages on a subsample of the vertices, the last on every vertex (with the
    # shape offset, which is fitted at every vertex, every stage on every vertex).
    coarse = None
    if hasattr(data, "subset") and shape is None:
        coarse = coarse_vertices(model.num_vertices, settings.coarse_vertices)
    plan = (("placement", placement, False, levels[0], iterations[0], coarse),
            ("neck", neck, False, levels[1], iterations[1], coarse),
            ("all", everything, True, levels[2], iterations[2], None))
    for name, mask, with_eta, level, count, subset in plan:
        if not count:
            continue
        if hasattr(data, "subset"):
            data.subset = subset
        after = (lambda s: shape.step(solver, s)) if (shape is not None and name == "all") else None
        state = solver.run_stage(state, mask, count, [level], with_eta, name, after)
    if hasattr(data, "subset"):
        data.subset = None
    rms = final_rms(lin, data, state, settings)
    solver._passes_done = solver._passes_total
    if progress is not None:
        progress(T)
    return assemble(model, solver, state, rms, time.perf_counter() - started)


def coarse_vertices(count: int, wanted: int) -> torch.Tensor | None:
    """Every k-th of ``count`` vertices, about ``wanted`` of them (None: all, when ``wanted`` is 0 or more)."""
    if wanted <= 0 or wanted >= count:
        return None
    return torch.arange(0, count, count // wanted)


def final_rms(lin: RigLinearisation, data, state: State, settings: FitSettings) -> np.ndarray:
    """The data term's unweighted RMS per frame (cm) at the final state."""
    out = np.zeros(len(state.rigid))
    for start in range(0, len(out), settings.chunk):
        index = slice(start, min(start + settings.chunk, len(out)))
        q = lin.pose(*state.frames(index), offset=state.offset)
        vertices, weights, targets, normals = data.rows(list(range(index.start, index.stop)), q)
        if vertices is not None:
            q = q[:, vertices]
        diff = q - targets
        squared = (diff * diff).sum(-1) if normals is None else (diff * normals).sum(-1) ** 2
        out[index] = ((weights * squared).sum(1) / weights.sum(1).clamp_min(1e-9)).sqrt().double().numpy()
        if hasattr(data, "point_rms"):   # scans: the points' own RMS distance, not their per-vertex means'
            out[index] = [data.point_rms[k] for k in range(index.start, index.stop)]
    return out


def joint_uncertainty(solver: Solver, settings: FitSettings) -> np.ndarray:
    """[J] degrees: per joint sqrt(trace / 3) of its 3x3 block of the inverse data Hessian (with E_rot and
    psi's pull), averaged over frames; NaN for the root."""
    lay = solver.layout
    H = solver.data_hessian.copy()
    H[:, lay.psi, lay.psi] += np.eye(lay.num_expressions) / settings.psi_scale**2
    H += 1e-6 * np.eye(lay.size)
    theta = np.arange(lay.size)[lay.theta]
    out = np.full(lay.num_joints, np.nan)
    try:
        covariance = np.linalg.inv(H)[:, theta][:, :, theta]                  # [T,3(J-1),3(J-1)]
    except np.linalg.LinAlgError:
        return out
    variances = np.einsum("tii->ti", covariance).reshape(len(H), -1, 3).sum(-1) / 3
    out[1:] = np.degrees(np.sqrt(np.clip(variances, 0, None))).mean(0)
    return out


def assemble(model: HeadNeckModel, solver: Solver, state: State, rms_cm: np.ndarray, seconds: float) -> FitResult:
    T = len(state.rigid)
    rotation, translation = placement_of(state)
    theta = torch.cat([torch.zeros(T, 1, 3), state.rigid[:, 6:].reshape(T, -1, 3)], 1)
    report = dict(solver.report)
    report.update(seconds=seconds, frames_per_second=T / max(seconds, 1e-9),
                  worst_frames=[int(i) for i in np.argsort(-rms_cm)[: min(5, T)]])
    return FitResult(
        theta=theta.numpy().astype(np.float32), psi=state.psi.numpy().astype(np.float32),
        tau=state.tau.numpy().astype(np.float32), eta=float(state.eta[0]),
        root_rotation=rotation.numpy().astype(np.float32), root_translation=translation.numpy().astype(np.float32),
        shape_offset=None if state.offset is None else state.offset.numpy().astype(np.float32),
        fit_rms_mm=(10 * rms_cm).astype(np.float32),
        joint_uncertainty_deg=joint_uncertainty(solver, solver.settings).astype(np.float32),
        report=report)


def check_finite_settings(settings: FitSettings) -> None:
    for name in ("noise_cm", "robust_scale_cm", "robust_start_cm"):
        if not (math.isfinite(getattr(settings, name)) and getattr(settings, name) > 0):
            raise ValueError(f"FitSettings.{name} must be positive, got {getattr(settings, name)}")
