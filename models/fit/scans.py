"""``fit_scans``: point clouds of any topology (partial, holes, noise, stray points).

Data term: point to surface, as point-to-plane at the nearest posed vertex (its area-weighted normal) plus a
small share of point to point (``FitSettings.scan_plane_share``), over the scan's points (a random subset of
``scan_points`` per frame).  Correspondences are the nearest vertices (``scipy.spatial.cKDTree`` on the
posed mesh) found again at every linearisation; a point farther than ``scan_max_distance_cm`` (or 2x the
current robust scale, early on) is a stray, the others are Geman-McClure-weighted one by one, then summed per
vertex (the sum of a vertex's squared point-to-plane distances is its weighted mean point's, exactly).  Only
scan to mesh: a mesh-to-scan term would pull the unseen half and the holes onto the scan.

Initial placement: the template fitted rigidly (trimmed point-to-plane ICP) from the 24 axis-aligned
orientations on the first frame (the capture's frame is arbitrary), the best four refined and the best of
them kept; every next frame starts from the previous.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree

from base.errors import InputError
from data.mesh_io import triangulate, vertex_normals
from models.fit.sequence import check_finite_settings, fit_sequence, initial_state
from models.fit.settings import FitResult, FitSettings
from models.fit.shape import ShapeOffset
from models.rig import HeadNeckModel

MIN_POINTS = 100


def check_clouds(clouds: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Each frame a finite [N,3] array with N >= ``MIN_POINTS``, or InputError naming the frame."""
    if len(clouds) == 0:
        raise InputError("clouds: no frames, expected at least one point cloud")
    out = []
    for k, cloud in enumerate(clouds):
        array = np.asarray(cloud)
        if array.ndim != 2 or array.shape[1] != 3:
            raise InputError(f"clouds: frame {k} has shape {list(array.shape)}, expected [N,3]")
        if len(array) < MIN_POINTS:
            raise InputError(f"clouds: frame {k} has {len(array)} points, expected at least {MIN_POINTS}")
        if not np.isfinite(array).all():
            raise InputError(f"clouds: frame {k} holds NaN or infinite coordinates")
        out.append(array.astype(np.float64))
    return out


def _rotations24() -> np.ndarray:
    """The 24 proper rotations that map the axes onto the axes."""
    out = []
    for perm in ((0, 1, 2), (1, 2, 0), (2, 0, 1), (1, 0, 2), (0, 2, 1), (2, 1, 0)):
        for signs in np.ndindex(2, 2, 2):
            m = np.zeros((3, 3))
            for row, column in enumerate(perm):
                m[row, column] = 1 - 2 * signs[row]
            if np.linalg.det(m) > 0:
                out.append(m)
    return np.stack(out)


def _turn(w: np.ndarray) -> np.ndarray:
    """The rotation matrix of the axis-angle vector ``w`` (Rodrigues)."""
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return np.eye(3)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]]) / angle
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def rigid_icp(tree: cKDTree, source: np.ndarray, normals: np.ndarray, target: np.ndarray, rotation: np.ndarray,
              translation: np.ndarray, iterations: int, keep: float = 0.8) -> tuple[np.ndarray, np.ndarray, float]:
    """Trimmed point-to-plane ICP of the scan points ``target`` onto the mesh (``source`` vertices, their
    ``normals``, ``tree`` a cKDTree on them): returns the mesh's placement in the scan (rotation,
    translation) and the trimmed RMS point-to-vertex distance (cm).  Point to plane, not point to point:
    from 40-50 degrees off a half-head scan, point to point stalls 20-30 degrees away (and the best-scored
    start then was a flipped head, 135-175 degrees off); point to plane reaches the right fit from there."""
    err = np.inf
    for _ in range(iterations):
        local = (target - translation) @ rotation          # the scan in the mesh's frame
        distance, index = tree.query(local)
        inlier = distance <= np.quantile(distance, keep)
        err = float(np.sqrt((distance[inlier] ** 2).mean()))
        p, q, n = local[inlier], source[index[inlier]], normals[index[inlier]]
        # Move the points by a small turn w and shift v: minimise sum (n . (p + w x p + v - q))^2.
        step = np.linalg.lstsq(np.concatenate([np.cross(p, n), n], 1), ((q - p) * n).sum(1), rcond=None)[0]
        rotation = rotation @ _turn(step[:3]).T
        translation = translation - rotation @ step[3:]
    return rotation, translation, err


def initial_placements(model: HeadNeckModel, clouds: list[np.ndarray]) -> tuple[torch.Tensor, torch.Tensor]:
    template = model.template.double().numpy()
    normals = vertex_normals(template, triangulate(model.rig.faces))
    tree = cKDTree(template)
    centre = template.mean(0)
    first = clouds[0]
    # Every orientation a few iterations, the best four to convergence: a front-half scan also fits the back
    # of the head fairly well early on.
    candidates = []
    for rotation in _rotations24():
        candidates.append(rigid_icp(tree, template, normals, first, rotation, first.mean(0) - rotation @ centre,
                                    10))
    candidates.sort(key=lambda c: c[2])
    best = min((rigid_icp(tree, template, normals, first, r, t, 30) for r, t, _ in candidates[:4]),
               key=lambda c: c[2])
    rotations, translations = [], []
    r, t = best[0], best[1]
    for cloud in clouds:
        r, t, _ = rigid_icp(tree, template, normals, cloud, r, t, 15)
        rotations.append(r)
        translations.append(t)
    return torch.tensor(np.stack(rotations), dtype=torch.float32), torch.tensor(np.stack(translations),
                                                                                 dtype=torch.float32)


class ScanData:
    """Correspondences from scan points to the nearest posed vertices, found again at each linearisation."""

    robust_inside = True

    def __init__(self, clouds: list[np.ndarray], faces: np.ndarray, settings: FitSettings):
        self.clouds = clouds
        self.tris = triangulate(faces)
        self.settings = settings
        self.robust_cm = settings.robust_start_cm
        self.point_rms: dict[int, float] = {}

    def rows(self, frames: list[int], q: torch.Tensor):
        s = self.settings
        limit = max(s.scan_max_distance_cm, 2 * self.robust_cm)
        posed = q.double().numpy()
        per_frame = []
        for k, frame in enumerate(frames):
            points = self.clouds[frame]
            distance, index = cKDTree(posed[k]).query(points, distance_upper_bound=limit)
            inlier = np.isfinite(distance)
            points, index = points[inlier], index[inlier]
            normals = vertex_normals(posed[k], self.tris)
            along = ((posed[k][index] - points) * normals[index]).sum(1)
            squared = along**2 + s.scan_plane_share * ((posed[k][index] - points) ** 2).sum(1)
            weight = (self.robust_cm**2 / (self.robust_cm**2 + squared)) ** 2
            self.point_rms[frame] = float(np.sqrt((along**2).mean())) if len(along) else float("nan")
            per_frame.append((index, points, weight, normals))
        vertices = np.unique(np.concatenate([f[0] for f in per_frame]))
        position = np.full(len(posed[0]), -1)
        position[vertices] = np.arange(len(vertices))
        n = len(vertices)
        weights = np.zeros((len(frames), n))
        targets = np.zeros((len(frames), n, 3))
        normals = np.zeros((len(frames), n, 3))
        for k, (index, points, weight, frame_normals) in enumerate(per_frame):
            slot = position[index]
            np.add.at(weights[k], slot, weight)
            np.add.at(targets[k], slot, weight[:, None] * points)
            normals[k] = frame_normals[vertices]
        targets /= np.maximum(weights, 1e-12)[..., None]
        # Unmatched vertices: weight 0, target at the vertex itself.
        empty = weights == 0
        targets[empty] = posed[:, vertices][empty]
        return (torch.tensor(vertices), torch.tensor(weights, dtype=torch.float32),
                torch.tensor(targets, dtype=torch.float32), torch.tensor(normals, dtype=torch.float32))


def fit_scans(model: HeadNeckModel, clouds: Sequence[np.ndarray], settings: FitSettings | None = None,
              progress: Callable[[int], None] | None = None) -> FitResult:
    """Fit the rig to point clouds (T arrays [N_t,3], cm, the capture's frame, any topology and count).

    Returns what ``fit_meshes`` does; ``fit_rms_mm`` is the RMS point-to-plane distance of the inlier
    points.  InputError names a frame with fewer than 100 points, a wrong shape or NaN.
    """
    settings = FitSettings() if settings is None else settings
    check_finite_settings(settings)
    clouds = check_clouds(clouds)
    rng = np.random.default_rng(settings.seed)
    used = [c[rng.choice(len(c), settings.scan_points, replace=False)] if len(c) > settings.scan_points else c
            for c in clouds]
    rotation, translation = initial_placements(model, used)
    state = initial_state(model, rotation, translation)
    shape = None
    if settings.fit_shape:

        shape = ShapeOffset(model, settings)
    data = ScanData(used, model.rig.faces, settings)
    return fit_sequence(model, data, state, settings, progress, shape)
