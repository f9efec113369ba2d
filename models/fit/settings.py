"""``FitSettings`` (the solver's knobs, each with its unit) and ``FitResult`` (what a fit returns).

Energy (every term a sum of squared *whitened* residuals, so that the Gauss-Newton Hessian is an inverse
covariance and ``joint_uncertainty_deg`` is in degrees):

- data: capture minus posed rig over ``noise_cm`` (per axis), robustly weighted (Geman-McClure, scale
  ``robust_scale_cm``, annealed from ``robust_start_cm`` over the stages);
- temporal: the second difference across frames of the placement, theta and tau over its ``*_acceleration``
  (per frame^2; psi is per frame);
- E_rot (Zhang et al., HACK, SIGGRAPH 2023): each joint's Euler angles outside ``data.joint_limits`` over
  ``limit_deg``;
- neck prior (``neck_prior``): "subaxial" is the paper's E_sim (adjacent joints rotate alike) on the pairs
  below C2 only (E_sim on every pair pulls C1-C2, which carries the head's turn, towards its neighbours);
- psi: a weak pull to zero (``psi_scale``); psi is kept in [0, 1].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class FitSettings:
    """Knobs of ``fit_meshes`` / ``fit_scans``; the defaults are the measured best (benchmarks/README.md,
    "Fitting HACK to captures")."""

    fit_shape: bool = False              # fit a per-sequence smooth offset of the rest mesh (another person)
    noise_cm: float = 0.1                # the capture's noise per axis (whitens the data term)
    robust_scale_cm: float = 0.5         # Geman-McClure scale of the data term at the last stage
    robust_start_cm: float = 4.0         # ... at the first stage (annealed geometrically)
    temporal: bool = True                # the smoothness term across frames (False: every frame alone)
    theta_acceleration_deg: float = 0.3  # std of a joint angle's second difference per frame^2
    rotation_acceleration_deg: float = 0.3   # ... of the placement's rotation
    translation_acceleration_cm: float = 0.05  # ... of the placement's translation
    tau_acceleration: float = 0.002      # ... of tau
    limit_deg: float = 1.0               # E_rot: std of an angle beyond its joint limit (0 disables E_rot)
    neck_prior: str = "subaxial"         # none | subaxial: E_sim on the pairs C6-C7 ... C2-C3 (measured,
                                         # benchmarks/README.md)
    neck_prior_deg: float = 0.5          # std of an adjacent pair's difference (anatomical frames)
    psi_scale: float = 3.0               # std of the weak pull of psi to zero
    iterations: tuple[int, int, int] = (2, 3, 6)  # Gauss-Newton iterations: placement, + neck, + all
    tolerance: float = 1e-4              # a stage ends once a step lowers the energy by less than this share
    damping: float = 1e-4                # initial Levenberg-Marquardt damping (relative to the diagonal)
    coarse_vertices: int = 2000          # meshes, no fit_shape: placement and neck stages on ~this many vertices
    hessian_vertices: int = 2000         # Gauss-Newton Hessian from about this many vertices (the gradient: all)
    workers: int = 1                     # meshes: overlapping windows of the sequence fitted at once, a process each
    window_overlap: int = 12             # ... frames shared by adjacent windows (each keeps its half)
    chunk: int = 16                      # frames linearised at once (memory ~ chunk * 14 MB on the real rig)
    shape_laplacian_cm: float = 0.003    # shape offset: std of its graph Laplacian (I - D^-1 A) per vertex
    shape_iterations: int = 300          # shape offset: conjugate-gradient iterations per step
    shape_scale_cm: float = 2.0          # shape offset: std of its pull to zero
    seed: int = 0                        # random choices (scan subsampling)
    # scans only
    scan_points: int = 8000              # scan points used per frame (random subset, ``seed``)
    scan_max_distance_cm: float = 1.5    # scan points farther from the rig than this are strays
    scan_plane_share: float = 0.1        # point-to-plane data term plus this share of point-to-point


@dataclass
class FitResult:
    """A fit of one sequence (``models.fit``'s interface; units cm, radians)."""

    theta: np.ndarray                  # [T,J,3] float32, theta[:, 0] == 0 (the root is in the placement)
    psi: np.ndarray                    # [T,E] float32
    tau: np.ndarray                    # [T] float32
    eta: float
    root_rotation: np.ndarray          # [T,3,3] float32: x_capture = root_rotation @ x_rig + root_translation
    root_translation: np.ndarray       # [T,3] float32, cm
    shape_offset: np.ndarray | None    # [V,3] float32 cm, or None when not fitted
    fit_rms_mm: np.ndarray             # [T] float32: the data term's RMS per frame, mm
    joint_uncertainty_deg: np.ndarray  # [J] float32: per joint the data's std (Gauss-Newton), NaN for the root
    report: dict                       # iterations, per-stage timings, ... (JSON-able)
