"""Levenberg-Marquardt over a whole sequence: per-frame unknowns coupled by the temporal term, eta shared.

The normal equations of T frames of P unknowns (``models.fit.linearise.FrameLayout``) are block-banded: the
data term and E_rot give one P x P block per frame, the second differences couple frames t and t +- 1, 2.
They are solved as one banded system (``scipy.linalg.solveh_banded``, lower bandwidth 2P: O(T P^3)), and
eta, which every frame sees, by its Schur complement (one more right-hand side).  Coarse to fine: the
stages free the placement, then theta, then psi, tau and eta (and the shape offset, ``models.fit.shape``).

A data term is an object with ``rows(frames, q) -> (vertices, weights [b,n], targets [b,n,3],
normals [b,n,3] | None)`` (``vertices`` [n] or None for all, the same for every frame of the call); the
residual is ``sqrt(w) (q - y)`` per axis (meshes), or ``sqrt(w) [n.(q - y); sqrt(share) (q - y)]``
(point-to-plane with a share of point-to-point, scans).
"""
from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import scipy.linalg
import torch

from base.rotations import axis_angle_to_euler
from data.joint_limits import euler_limits
from models.fit.linearise import RigLinearisation, rodrigues
from models.fit.settings import FitSettings


@dataclass
class State:
    """The unknowns of a sequence (torch float32): rigid [T, 6 + 3(J-1)], psi [T,E], tau [T], eta [1],
    reference [3,3] (the placement's rotation is exp(r_t) @ reference), offset [V,3] or None."""

    rigid: torch.Tensor
    psi: torch.Tensor
    tau: torch.Tensor
    eta: torch.Tensor
    reference: torch.Tensor
    offset: torch.Tensor | None = None

    def copy(self) -> State:
        return State(self.rigid.clone(), self.psi.clone(), self.tau.clone(), self.eta.clone(),
                     self.reference, None if self.offset is None else self.offset.clone())

    def frames(self, index: slice):
        rigid = self.rigid[index]
        return (rigid, self.psi[index], self.tau[index], self.eta.expand(len(rigid)),
                self.reference.expand(len(rigid), 3, 3))


@dataclass
class System:
    """The energy at one state and its normal equations (H [T,P,P] and g [T,P] with every prior, before the
    damping), the eta terms, the psi weights held at a bound [T,P], the data term's RMS [T] and Hessian."""

    total: float
    robust_cm: float
    H: np.ndarray
    g: np.ndarray
    eta_terms: tuple
    bound: np.ndarray
    rms: np.ndarray
    data_hessian: np.ndarray
    psi_subsampled: np.ndarray


def geman_mcclure(squared: torch.Tensor, scale: float) -> torch.Tensor:
    """IRLS weight of Geman-McClure's rho(r) = r^2 s^2 / (r^2 + s^2) at squared residual norms (cm^2)."""
    return (scale**2 / (scale**2 + squared)) ** 2


class Solver:
    """One sequence's Levenberg-Marquardt (see the module docstring)."""

    def __init__(self, lin: RigLinearisation, settings: FitSettings, data, num_frames: int,
                 progress: Callable[[int], None] | None = None):
        self.lin, self.settings, self.data, self.T = lin, settings, data, num_frames
        self.layout = lin.layout
        self.P = self.layout.size
        self.progress = progress
        self.damping = settings.damping
        self.report: dict = {"iterations": [], "stages": []}
        lower, upper = euler_limits()
        self.limits = (lower[1:], upper[1:])
        self.axes = lin.model.anatomical_axes[1:].float()
        self.neck = self.neck_matrix()
        self.extra_energy: Callable[[State], float] | None = None   # the shape offset's prior, when fitted
        self._passes_total = 1
        self._passes_done = 0

    # ------------------------------------------------------------------ weights of the temporal term

    def temporal_weights(self) -> np.ndarray:
        """[P] inverse variances of each unknown's second difference (zero without the temporal term; psi is
        fitted per frame)."""
        s, lay = self.settings, self.layout
        w = np.zeros(self.P)
        if not s.temporal or self.T < 3:
            return w
        w[lay.rotation] = 1 / math.radians(s.rotation_acceleration_deg) ** 2
        w[lay.translation] = 1 / s.translation_acceleration_cm**2
        w[lay.theta] = 1 / math.radians(s.theta_acceleration_deg) ** 2
        w[lay.tau] = 1 / s.tau_acceleration**2
        return w

    # ------------------------------------------------------------------ one linearisation of every frame

    def normal_equations(self, state: State, robust_cm: float, with_eta: bool):
        """Per frame H [T,P,P], g [T,P] (gradient of half the energy), data energy [T], the eta column
        [T,P] and its diagonal entry and gradient; also the unweighted RMS per frame (cm).

        The gradient is exact over every row (``RigLinearisation.gradient``: the Jacobian's structure, never
        the Jacobian); the Gauss-Newton Hessian is the Jacobian's Gram on every k-th row's vertex, times k
        (``FitSettings.hessian_vertices`` of them) but for psi's own block, from every vertex (with the chunk's
        mean weights): the fixed point is the exact one, the steps nearly as good as with all vertices, at a
        fraction of the cost on the real rig."""
        T, P = self.T, self.P
        H = np.zeros((T, P, P))
        g = np.zeros((T, P))
        energy = np.zeros(T)
        rms = np.zeros(T)
        h_eta = np.zeros((T, P))
        eta_hh, eta_g = 0.0, 0.0
        self.psi_subsampled = np.zeros((T, self.layout.num_expressions, self.layout.num_expressions))
        inv_noise2 = 1.0 / self.settings.noise_cm**2
        share = self.settings.scan_plane_share
        for start in range(0, T, self.settings.chunk):
            index = slice(start, min(start + self.settings.chunk, T))
            frames = list(range(index.start, index.stop))
            unknowns = state.frames(index)
            self.data.robust_cm = robust_cm
            if hasattr(self.data, "subset"):   # rows known before posing (meshes): pose only those vertices
                skinned = self.lin.skin(*unknowns, offset=state.offset, vertices=self.data.subset)
                vertices, weights, targets, normals = self.data.rows(frames, skinned.q)
                q = skinned.q
            else:
                probe = self.lin.pose(*unknowns, offset=state.offset)
                vertices, weights, targets, normals = self.data.rows(frames, probe)
                q = probe if vertices is None else probe[:, vertices]
                skinned = self.lin.skin(*unknowns, offset=state.offset, vertices=vertices)
            diff = q - targets                                               # [b,n,3]
            if normals is None:
                squared = (diff * diff).sum(-1)
            else:
                along = (diff * normals).sum(-1)
                squared = along**2 + share * (diff * diff).sum(-1)
            if getattr(self.data, "robust_inside", False):   # the data term weighs its points itself
                w = weights * inv_noise2
            else:
                w = weights * geman_mcclure(squared, robust_cm) * inv_noise2   # [b,n]
            total = weights.sum(1).clamp_min(1e-9)
            rms[index] = (((weights * squared).sum(1) / total).sqrt()).double().numpy()
            if getattr(self.data, "robust_inside", False):
                energy[index] = (w * squared).sum(1).double().numpy()
            else:   # Geman-McClure's rho, r^2 s^2 / (r^2 + s^2), whose gradient the IRLS weights give
                rho_gm = squared * robust_cm**2 / (robust_cm**2 + squared)
                energy[index] = (weights * inv_noise2 * rho_gm).sum(1).double().numpy()
            # The information-weighted residual A (q - y): A = w I (meshes) or w (n n^T + share I) (scans).
            if normals is None:
                rho = w[..., None] * diff
            else:
                rho = w[..., None] * (normals * along[..., None] + share * diff)
            grad, grad_eta, _ = self.lin.gradient(*unknowns, rho, offset=state.offset, vertices=vertices,
                                                  skinned=skinned)
            g[index] = grad.double().numpy()
            eta_g += float(grad_eta.sum())
            # The Hessian on every k-th row.
            n = q.shape[1]
            stride = max(1, n // self.settings.hessian_vertices)
            pick = torch.arange(0, n, stride)
            scale = n / len(pick)
            sub = pick if vertices is None else vertices[pick]
            _, jac, deta, _ = self.lin.linearise(*unknowns, offset=state.offset, vertices=sub,
                                                 derivatives=skinned.derivatives)
            root = (w[:, pick] * scale).sqrt()[..., None]
            if normals is None:
                rows_j = (root[..., None] * jac).reshape(len(frames), -1, P)
                rows_e = (root * deta).reshape(len(frames), -1)
            else:
                nrm = normals[:, pick]
                nj = torch.einsum("bnc,bncp->bnp", nrm, jac)
                rows_j = torch.cat([(root * nj)[:, :, None], math.sqrt(share) * root[..., None] * jac], dim=2)
                rows_j = rows_j.reshape(len(frames), -1, P)
                ne = (nrm * deta).sum(-1)
                rows_e = torch.cat([(root[..., 0] * ne)[..., None], math.sqrt(share) * root * deta], -1).reshape(
                    len(frames), -1)
            H[index] = (rows_j.transpose(1, 2) @ rows_j).double().numpy()
            self.psi_subsampled[index] = H[index][:, self.layout.psi, self.layout.psi]
            # psi's block from every vertex (expressions are local: a subsample misses the small ones), with
            # the chunk's mean information in rest space, L^T A L.
            information = self.lin.mean_metric(skinned, w * (1.0 if normals is None else share))   # [n,3,3]
            if normals is not None:
                rest_normals = self.lin.pull_back(skinned, normals)
                outer = rest_normals[..., :, None] * rest_normals[..., None, :]           # [b,n,3,3]
                information = information + (w[..., None, None] * outer).mean(0)
            gram = self.lin.expression_gram(information, vertices).double().numpy()
            H[index, self.layout.psi, self.layout.psi] = gram
            if with_eta:
                h_eta[index] = (rows_j.transpose(1, 2) @ rows_e[..., None])[..., 0].double().numpy()
                eta_hh += float((rows_e * rows_e).sum())
            self._passes_done += len(frames) / T
            if self.progress is not None:
                self.progress(min(T, int(T * self._passes_done / self._passes_total)))
        return H, g, energy, rms, (h_eta, eta_hh, eta_g)

    # ------------------------------------------------------------------ priors on one frame

    def limit_terms(self, state: State):
        """E_rot (joint limits) per frame: H [T,P,P], g [T,P], energy [T]."""
        T, P, lay = self.T, self.P, self.layout
        H = np.zeros((T, P, P))
        g = np.zeros((T, P))
        energy = np.zeros(T)
        if self.settings.limit_deg <= 0:
            return H, g, energy
        sigma = math.radians(self.settings.limit_deg)
        theta = state.rigid[:, lay.theta].reshape(T, -1, 3).clone().requires_grad_(True)
        anatomical = torch.einsum("jab,tja->tjb", self.axes, theta)
        euler = axis_angle_to_euler(anatomical)
        lower, upper = self.limits
        residual = ((torch.relu(euler - upper) - torch.relu(lower - euler)) / sigma).reshape(T, -1)  # [T,K]
        active = residual.detach().abs().sum(0) > 0
        if not bool(active.any()):
            return H, g, energy
        jac = torch.zeros(T, residual.shape[1], theta[0].numel())
        for k in torch.nonzero(active).flatten().tolist():
            (grad,) = torch.autograd.grad(residual[:, k].sum(), theta, retain_graph=True)
            jac[:, k] = grad.reshape(T, -1)
        r = residual.detach().double().numpy()
        j = jac.double().numpy()
        H[:, lay.theta, lay.theta] = np.einsum("tki,tkl->til", j, j)
        g[:, lay.theta] = np.einsum("tki,tk->ti", j, r)
        energy[:] = (r**2).sum(1)
        return H, g, energy

    def neck_matrix(self) -> np.ndarray:
        """The neck prior's constant Hessian on theta[1:] [3(J-1), 3(J-1)] (zero for ``none``)."""
        size = 3 * (self.layout.num_joints - 1)
        prior = self.settings.neck_prior
        if prior == "none":
            return np.zeros((size, size))
        if prior != "subaxial":
            raise ValueError(f"FitSettings.neck_prior={prior!r}: expected none or subaxial")
        axes = self.axes.double().numpy()                     # [J-1,3,3]: anatomical = axes^T theta
        rows = []
        for a in range(0, 4):                                 # joints 1..5 (c6c7..c2c3) -> rest index 0..4
            k = np.zeros((3, size))
            k[:, 3 * a: 3 * a + 3] = axes[a].T
            k[:, 3 * a + 3: 3 * a + 6] = -axes[a + 1].T
            rows.append(k)
        k = np.concatenate(rows) / math.radians(self.settings.neck_prior_deg)
        return k.T @ k

    def psi_terms(self, state: State):
        """The weak pull of psi to zero: diagonal [E], g [T,E], energy [T]."""
        w = 1.0 / self.settings.psi_scale**2
        psi = state.psi.double().numpy()
        return w, w * psi, w * (psi**2).sum(1)

    # ------------------------------------------------------------------ the banded solve

    def temporal_energy(self, values: np.ndarray, weights: np.ndarray) -> float:
        if self.T < 3 or not weights.any():
            return 0.0
        second = values[:-2] - 2 * values[1:-1] + values[2:]
        return float((second**2 * weights).sum())

    def solve(self, H, g, weights, mask, eta_terms, damping: float, bound: np.ndarray | None = None):
        """Solve (H + temporal + damping) dx = -g for the free unknowns (``mask`` [P]); returns dx [T,P] and
        d_eta.  psi, which the temporal term does not couple, is eliminated per frame first (Schur
        complement), so the banded system holds only the placement, theta and tau (lower bandwidth 2 x 28)."""
        T, P, lay = self.T, self.P, self.layout
        H = H.copy()
        g = g.copy()
        h_eta, eta_hh, eta_g = eta_terms
        h_eta = h_eta.copy()
        free = mask.astype(bool)
        H[:, ~free, :] = 0
        H[:, :, ~free] = 0
        g[:, ~free] = 0
        h_eta[:, ~free] = 0
        if bound is not None:   # [T,P] unknowns held at a bound this step (psi at 0 or 1, pushed outwards)
            H[bound[:, :, None] | bound[:, None, :]] = 0
            g[bound] = 0
            h_eta[bound] = 0
        diag = np.einsum("tii->ti", H)
        diag += damping * diag + 1e-9
        diag[:, ~free] = 1.0
        if bound is not None:
            diag[bound] = 1.0
        local = np.arange(P)[lay.psi]
        coupled = np.setdiff1d(np.arange(P), local)
        hll = H[:, local][:, :, local]
        hcl = H[:, coupled][:, :, local]
        hll_inv = np.linalg.inv(hll)
        k = hcl @ hll_inv                                                      # [T,C,E]
        hcc = H[:, coupled][:, :, coupled] - k @ hcl.transpose(0, 2, 1)
        gc = g[:, coupled] - (k @ g[:, local, None])[..., 0]
        hc = h_eta[:, coupled] - (k @ h_eta[:, local, None])[..., 0]
        w = (weights * free)[coupled]
        C = len(coupled)
        n = T * C
        bands = 2 * C if T >= 3 and w.any() else C - 1
        ab = np.zeros((bands + 1, n))
        for d in range(C):
            ab[d].reshape(T, C)[:, : C - d] = np.diagonal(hcc, offset=-d, axis1=1, axis2=2)
        if bands >= 2 * C:
            # D^T D of the second differences: diagonal (1, 5, 6, ..., 6, 5, 1), first (-2, -4, ..., -4, -2),
            # second (1, ..., 1).
            main = np.full(T, 6.0)
            main[[0, -1]] = 1
            main[[1, -2]] = 5
            first = np.full(T - 1, -4.0)
            first[[0, -1]] = -2
            ab[0] += (main[:, None] * w).reshape(-1)
            ab[C, : n - C] += (first[:, None] * w).reshape(-1)
            ab[2 * C, : n - 2 * C] += np.tile(w, T - 2)
        rhs = [-gc.reshape(-1)]
        if eta_hh > 0:
            rhs.append(hc.reshape(-1))
        # Nearly singular after eliminating psi: a little more damping on the banded part.
        for attempt in range(3):
            try:
                solution = scipy.linalg.solveh_banded(ab, np.stack(rhs, 1), lower=True)
                break
            except np.linalg.LinAlgError:
                if attempt == 2:
                    raise
                ab[0] += np.abs(ab[0]) * 10.0 ** (attempt - 3) + 1e-6
        dc = solution[:, 0]
        d_eta = 0.0
        if eta_hh > 0:
            z = solution[:, 1]
            hl = h_eta[:, local]
            hll_reduced = eta_hh * (1 + damping) - np.einsum("te,tef,tf->", hl, hll_inv, hl)
            g_reduced = eta_g - np.einsum("te,tef,tf->", hl, hll_inv, g[:, local])
            d_eta = (-g_reduced - hc.reshape(-1) @ dc) / max(hll_reduced - hc.reshape(-1) @ z, 1e-12)
            dc = dc - z * d_eta
        dc = dc.reshape(T, C)
        dx = np.zeros((T, P))
        dx[:, coupled] = dc
        rhs_l = -g[:, local] - (hcl.transpose(0, 2, 1) @ dc[..., None])[..., 0] - h_eta[:, local] * d_eta
        dx[:, local] = (hll_inv @ rhs_l[..., None])[..., 0]
        return dx, d_eta

    # ------------------------------------------------------------------ the stages

    def temporal_gradient(self, values: np.ndarray, weights: np.ndarray) -> np.ndarray:
        """Gradient of half the temporal energy: D^T D x per unknown, weighted [T,P]."""
        out = np.zeros_like(values)
        if self.T < 3 or not weights.any():
            return out
        second = values[:-2] - 2 * values[1:-1] + values[2:]
        out[:-2] += second
        out[1:-1] -= 2 * second
        out[2:] += second
        return out * weights

    def flat(self, state: State) -> np.ndarray:
        return torch.cat([state.rigid, state.psi, state.tau[:, None]], 1).double().numpy()

    def apply(self, state: State, dx: np.ndarray, d_eta: float) -> State:
        new = state.copy()
        lay = self.layout
        step = torch.tensor(dx, dtype=torch.float32)
        # Steps are capped (0.2 rad, 2 cm, 0.05 in tau, eta kept in [0, 3]): a far step is a poor linearisation.
        cap = torch.tensor([0.2] * 3 + [2.0] * 3 + [0.2] * (lay.theta.stop - lay.theta.start))
        new.rigid = state.rigid + torch.maximum(torch.minimum(step[:, lay.rigid], cap), -cap)
        new.psi = (state.psi + step[:, lay.psi]).clamp(0, 1)
        new.tau = state.tau + step[:, lay.tau].clamp(-0.05, 0.05)
        new.eta = (state.eta + float(np.clip(d_eta, -0.5, 0.5))).clamp(0, 3)
        return new

    def system(self, state: State, robust_cm: float, with_eta: bool, weights: np.ndarray) -> System:
        """The energy at ``state`` and its damped-free normal equations, every term included."""
        H, g, data_energy, rms, eta_terms = self.normal_equations(state, robust_cm, with_eta)
        HL, gL, eL = self.limit_terms(state)
        lay = self.layout
        theta = state.rigid[:, lay.theta].double().numpy()
        HL[:, lay.theta, lay.theta] += self.neck
        gL[:, lay.theta] += theta @ self.neck
        eL = eL + np.einsum("ti,ij,tj->t", theta, self.neck, theta)
        x = self.flat(state)
        wp, gp, ep = self.psi_terms(state)
        total = (data_energy.sum() + eL.sum() + self.temporal_energy(x, weights) + ep.sum()
                 + (self.extra_energy(state) if self.extra_energy else 0.0))
        data_hessian = H.copy()
        H += HL
        g += gL + self.temporal_gradient(x, weights)
        H[:, lay.psi, lay.psi] += np.eye(lay.num_expressions) * wp
        g[:, lay.psi] += gp
        # Projected Gauss-Newton on psi's box [0, 1]: a weight at a bound that the gradient pushes outwards is
        # held for this step (clamping after a free step stalls: measured 0.6 against 0.2 mm).
        psi = state.psi.double().numpy()
        bound = np.zeros(g.shape, bool)
        bound[:, lay.psi] = ((psi <= 0) & (g[:, lay.psi] > 0)) | ((psi >= 1) & (g[:, lay.psi] < 0))
        return System(float(total), robust_cm, H, g, eta_terms, bound, rms, data_hessian, self.psi_subsampled)

    def run_stage(self, state: State, mask: np.ndarray, iterations: int, robust: list[float], with_eta: bool,
                  name: str, after_step: Callable[[State], State] | None = None) -> State:
        """At most ``iterations`` accepted steps of Levenberg-Marquardt on the unknowns of ``mask``; a step that
        raises the energy is taken back (the linearisation before it is kept, not recomputed) with ten times
        the damping; the stage ends early once an accepted step lowers the energy by less than
        ``FitSettings.tolerance`` of it."""
        weights = self.temporal_weights()
        started = time.perf_counter()
        previous: tuple[State, System] | None = None   # the last state a step was taken from
        current: System | None = None                   # the linearisation of ``state`` when already known
        reverted = converged = False
        k = linearisations = 0
        while k < iterations and linearisations < 3 * iterations:
            robust_cm = robust[min(k, len(robust) - 1)]
            if current is None:
                current = self.system(state, robust_cm, with_eta, weights)
                linearisations += 1
            last = None if previous is None else previous[1]
            worse = not np.isfinite(current.total) or (last is not None and current.total > last.total * (1 + 1e-6)
                                                       and last.robust_cm == robust_cm)
            if worse and previous is not None:
                state, current = previous    # the step made it worse: back, more damping, and again
                self.damping *= 10
                reverted = True
                continue
            if not reverted:                 # an accepted step (not the same state after a rejected one)
                self.damping = max(self.damping / 3, 1e-7)
                if last is not None and last.robust_cm == robust_cm and \
                        last.total - current.total <= self.settings.tolerance * last.total:
                    converged = True
                    break
            reverted = False
            self.data_hessian, self.rms, self.psi_subsampled = current.data_hessian, current.rms, current.psi_subsampled
            try:
                if not (np.isfinite(current.H).all() and np.isfinite(current.g).all()):
                    raise np.linalg.LinAlgError("non-finite normal equations")
                try:
                    dx, d_eta = self.solve(current.H, current.g, weights, mask, current.eta_terms, self.damping,
                                           current.bound)
                except np.linalg.LinAlgError:
                    # psi's block from every vertex against the subsampled cross terms can leave the reduced
                    # system indefinite; with the subsample's own block added it is positive definite.
                    H = current.H.copy()
                    H[:, self.layout.psi, self.layout.psi] += current.psi_subsampled
                    dx, d_eta = self.solve(H, current.g, weights, mask, current.eta_terms, self.damping,
                                           current.bound)
            except np.linalg.LinAlgError as error:   # no step from here: back to the last state, more damping
                self.report.setdefault("failed_solves", []).append(f"{name}: {error}")
                if previous is not None:
                    state, current = previous
                self.damping *= 10
                linearisations += 1      # counts towards the attempts' bound
                continue
            previous = (state, current)
            state = self.apply(state, dx, d_eta if with_eta else 0.0)
            current = None
            if after_step is not None:
                state = after_step(state)
            self.report["iterations"].append({"stage": name, "energy": previous[1].total, "robust_cm": robust_cm,
                                              "damping": self.damping})
            k += 1
        self.report["stages"].append({"stage": name, "seconds": time.perf_counter() - started,
                                      "attempts": linearisations, "converged": converged})
        return state


def placement_of(state: State) -> tuple[torch.Tensor, torch.Tensor]:
    """root_rotation [T,3,3], root_translation [T,3] of a state."""
    return rodrigues(state.rigid[:, 0:3]) @ state.reference, state.rigid[:, 3:6]
