"""What the rig tells the tracker: pixels per tau unit, and where in the kernel the match should look.

- :func:`rig_px_per_tau`: pixels of upward image motion of the larynx point per tau unit, in the
  default neck view at rest (the larynx point projected at tau = -delta and +delta).
- :func:`calibrate_window`: the match window's vertical offset and height.  Under head motion the
  larynx region shears (when the neck flexes its top moves 2.5-4 times as far as its bottom) and when
  the jaw opens the chin comes down over the top of the larynx and drags the skin of the upper neck
  down; a match weighted towards the larynx's top then moves further than the larynx point.  The rig
  is rendered in a set of calibration poses (tau, flexion, lateral bending, axial rotation, the jaw
  opening where the rig has a ``jawOpen`` expression, and combinations; normal-map noise 0.05), each
  frame is searched around the true larynx point with each candidate window, and the window whose
  positions follow the larynx point best (least RMS error relative to the rest frame's) is kept:
  the region the jaw can reach and the sheared top weigh little in it.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import torch

from motion.track.config import TrackerConfig, WindowConfig
from motion.track.kernel import CONTEXT_MARGIN, LarynxKernel, with_window
from motion.track.match import LarynxTracker
from scene.render import DEFAULT_CM_PER_PX, NeckRenderer, neck_camera

# Candidate windows at 0.08 cm/px: offsets below the kernel's centre and heights (pixels).
WINDOW_OFFSETS_PX = (0.0, 2.0, 4.0, 6.0, 8.0, 10.0, 12.0, 14.0, 16.0, 18.0)
WINDOW_SIGMAS_PX = (10.0, 12.0, 14.0, 16.0)
CALIBRATION_NOISE = 0.05


def rig_px_per_tau(rig, cm_per_px: float = DEFAULT_CM_PER_PX, delta: float = 0.02, perspective: bool = False) -> float:
    """Pixels of upward image motion of the larynx point per tau unit, in the default neck view at rest."""
    renderer = NeckRenderer(rig, neck_camera(rig, 64, cm_per_px, perspective))
    _, pixels = renderer.pose(rig.neutral(2), tau=torch.tensor([-delta, delta]))
    return float(pixels[0, 1] - pixels[1, 1]) / (2 * delta)


def calibration_poses(rig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta [n,J,3] anatomical radians spread over the joints, psi [n,E], tau [n]) of the calibration
    frames; the first is the rest pose."""
    rows = [(0, 0, 0, 0.0, 0.0)]                                       # flexion, axial, bending (deg), tau, jaw
    rows += [(0, 0, 0, tau, 0.0) for tau in (-0.02, 0.015, 0.03, 0.045, 0.06)]
    rows += [(f, 0, 0, 0.0, 0.0) for f in (-15, -8, 8, 15)]
    rows += [(0, a, 0, 0.0, 0.0) for a in (-12, 12)] + [(0, 0, b, 0.0, 0.0) for b in (-12, 12)]
    rows += [(-10, 0, 0, 0.04, 0.0), (10, 0, 0, 0.04, 0.0)]
    names = list(rig.expression_names)
    if "jawOpen" in names:
        rows += [(0, 0, 0, 0.0, jaw) for jaw in (0.3, 0.6, 0.9)] + [(0, 0, 0, 0.03, 0.5), (8, 0, 0, 0.0, 0.6)]
    table = np.array(rows, dtype=np.float64)
    theta = np.repeat(np.radians(table[:, None, :3]) / rig.num_joints, rig.num_joints, axis=1)
    psi = np.zeros((len(table), rig.num_expressions))
    if "jawOpen" in names:
        psi[:, names.index("jawOpen")] = table[:, 4]
    return theta, psi, table[:, 3]


def calibrate_window(kernel: LarynxKernel, rig, config: TrackerConfig | None = None, seed: int = 0,
                     offsets=WINDOW_OFFSETS_PX, sigmas=WINDOW_SIGMAS_PX) -> LarynxKernel:
    """The kernel with its match window calibrated on ``rig`` (see the module doc).

    Args:
        kernel: a kernel of the rig (``rig_kernel``), whose ``cm_per_px`` sets the view's scale.
        config: the tracker's settings (band-pass, search band; default ``TrackerConfig()``).
        seed: of the calibration frames' noise.  offsets, sigmas: the candidates, pixels at 0.08 cm/px.
    Returns:
        the kernel with ``window`` = the best (offset_y, sigma_y) in its own pixels.
    """
    config = config or TrackerConfig()
    cm_per_px = kernel.cm_per_px or DEFAULT_CM_PER_PX
    factor = DEFAULT_CM_PER_PX / cm_per_px
    width, height = kernel.size
    camera = neck_camera(rig, max(width, height) + 2 * CONTEXT_MARGIN, cm_per_px)
    theta, psi, tau = calibration_poses(rig)
    theta_t = rig.from_anatomical(torch.tensor(theta, dtype=torch.float32))
    render, truth = NeckRenderer(rig, camera).render_with_truth(theta_t, torch.tensor(psi, dtype=torch.float32),
                                                                torch.tensor(tau, dtype=torch.float32))
    rng = np.random.default_rng(seed)
    frames = render.normals.numpy()
    noisy = frames + rng.normal(0.0, CALIBRATION_NOISE, frames.shape).astype(np.float32)
    noisy /= np.maximum(np.linalg.norm(noisy, axis=-1, keepdims=True), 1e-6)
    frames = np.where(render.mask.numpy()[..., None], noisy, 0.0).astype(np.float32)
    truth = truth.numpy().astype(np.float64)
    best, best_cost = None, np.inf
    for sigma in sigmas:
        for offset in offsets:
            candidate = with_window(kernel, offset * factor, sigma * factor)
            tracker = LarynxTracker(candidate, replace(config, window=WindowConfig(config.window.sigma_x_px)))
            rows = np.array([tracker.search(frame, tuple(point))[1] for frame, point in zip(frames, truth)])
            error = (rows - truth[:, 1]) - (rows[0] - truth[0, 1])
            cost = float(np.sqrt(np.mean(error ** 2)))
            if cost < best_cost:
                best, best_cost = (offset * factor, sigma * factor), cost
    return with_window(kernel, *best)
