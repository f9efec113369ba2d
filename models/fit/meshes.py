"""``fit_meshes``: registered meshes in the rig's topology (vertex n of the capture is vertex n of the rig).

Data term: vertex to vertex, ``|q_n - y_n|^2 / noise^2``, Geman-McClure-weighted.  The initial placement per
frame is the weighted Kabsch fit of the template's lower neck (the skin of c7t1 and c6c7) to the capture.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Callable

import numpy as np
import torch

from base.errors import InputError
from models.fit.sequence import check_finite_settings, fit_sequence, initial_state, kabsch
from models.fit.settings import FitResult, FitSettings
from models.fit.shape import ShapeOffset
from models.fit.windows import fit_in_windows
from models.rig import HeadNeckModel


class MeshData:
    """Known correspondences: the capture's vertices [T,V,3] (cm) are the targets of the rig's.

    ``subset`` (the rows' vertices, known before posing: the solver poses only those) is every vertex (None)
    or a subsample, whose weights are scaled by V / len(subset) so that the data term keeps its weight
    against the priors."""

    def __init__(self, vertices: torch.Tensor, weights: torch.Tensor | None = None):
        self.vertices = vertices
        self.weights = torch.ones(vertices.shape[:2]) if weights is None else weights   # [T,V]
        self.subset: torch.Tensor | None = None

    def rows(self, frames: list[int], q: torch.Tensor):
        if self.subset is None:
            return None, self.weights[frames], self.vertices[frames], None
        scale = self.vertices.shape[1] / len(self.subset)
        return (self.subset, scale * self.weights[frames][:, self.subset], self.vertices[frames][:, self.subset],
                None)


def check_meshes(model: HeadNeckModel, vertices) -> np.ndarray:
    """[T,V,3] finite float array, or InputError naming the frame and what was expected."""
    array = np.asarray(vertices)
    if array.ndim != 3 or array.shape[2] != 3 or array.shape[0] < 1:
        raise InputError(f"vertices: shape {list(array.shape)}, expected [T,{model.num_vertices},3] (T >= 1)")
    if array.shape[1] != model.num_vertices:
        raise InputError(f"vertices: {array.shape[1]} vertices per frame, the rig has {model.num_vertices}")
    bad = ~np.isfinite(array).all(axis=(1, 2))
    if bad.any():
        raise InputError(f"vertices: frame {int(np.flatnonzero(bad)[0])} holds NaN or infinite coordinates")
    return array.astype(np.float32)


def fit_meshes(model: HeadNeckModel, vertices: np.ndarray, settings: FitSettings | None = None,
               progress: Callable[[int], None] | None = None) -> FitResult:
    """Fit the rig to registered meshes ``vertices`` [T,V,3] (cm, the capture's frame, the rig's vertex order).

    Returns per frame the placement, theta (theta[:, 0] = 0), psi, tau; per sequence eta (and the shape
    offset when ``settings.fit_shape``).  InputError on a wrong shape or non-finite frame.
    """
    settings = FitSettings() if settings is None else settings
    check_finite_settings(settings)
    targets = torch.tensor(check_meshes(model, vertices))
    return fit_weighted_meshes(model, targets, None, settings, progress)


def fit_weighted_meshes(model: HeadNeckModel, targets: torch.Tensor, weights: torch.Tensor | None,
                        settings: FitSettings, progress: Callable[[int], None] | None = None) -> FitResult:
    """``fit_meshes`` on checked targets [T,V,3] with per-vertex weights [T,V] (None: all 1; 0 = unseen); in
    ``settings.workers`` overlapping windows at once (``models.fit.windows``) unless the shape is fitted."""
    if settings.workers > 1 and not settings.fit_shape:
        one = dataclasses.replace(settings, workers=1)

        def window(frames: slice, window_progress: Callable[[int], None] | None) -> FitResult:
            return fit_weighted_meshes(model, targets[frames], None if weights is None else weights[frames], one,
                                       window_progress)
        return fit_in_windows(window, len(targets), settings.workers, settings.window_overlap, progress)
    lower_neck = (model.skin_weights[:, 0] + model.skin_weights[:, 1]).float()
    seen = lower_neck if weights is None else lower_neck * weights.float().mean(0)
    rotation, translation = kabsch(model.template.float(), targets, seen)
    state = initial_state(model, rotation, translation)
    shape = None
    if settings.fit_shape:
        shape = ShapeOffset(model, settings)
    return fit_sequence(model, MeshData(targets, weights), state, settings, progress, shape)
