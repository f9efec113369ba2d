"""Morph targets beyond the expressions: the larynx slide as hat-weighted targets over tau, the pose
correctives as one target per feature.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from models.rig import HeadNeckModel

DEFAULT_LARYNX_ERROR_CM = 0.01   # a fifth of the 0.05 cm the whole export is held to
MAX_LARYNX_TARGETS = 256


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
