"""``fit_scans``: point clouds of any topology (partial, holes, noise, stray points).

Data term: point to surface, as point-to-plane at the nearest posed vertex (its area-weighted normal) plus a
small share of point to point (``FitSettings.scan_plane_share``), over the scan's points (a random subset of
``scan_points`` per frame).  Correspondences are the nearest vertices (``scipy.spatial.cKDTree`` on the
posed mesh) found again at every linearisation; a point farther than ``scan_max_distance_cm`` (or 2x the
current robust scale, early on) is a stray, the others are Geman-McClure-weighted one by one, then summed per
vertex (the sum of a vertex's squared point-to-plane distances is its weighted mean point's, exactly).  Only
scan to mesh: a mesh-to-scan term would pull the unseen half and the holes onto the scan.

Start: the template fitted rigidly (trimmed point-to-plane ICP) from the 24 axis-aligned orientations on the
first frame (the capture's frame is arbitrary), the best four refined and the best of them kept; every next
frame starts from the previous.  The head is most of the template, so this rigid fit follows the head and
leaves the torso off by the neck's bend (40-60 degrees in ``benchmarks/fit_app_check.py``'s nod, too far for
the solver).  So the head is refined alone (model-to-scan ICP of its vertices) and held, and the neck's bend
is searched (``NeckSearch``): candidate turns of the head relative to the torso, split over C6-C7 ... OC1 in
two ways (by range of motion, and evenly), each placing the torso so that the head stays, scored by the
neck's capped distances to the scan; the first frame over the neck's range, every next one near its
constant-velocity prediction.  The solver starts from that placement and theta.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from scipy.spatial import cKDTree

from base.errors import InputError
from base.rotations import matrix_to_axis_angle
from data.joint_limits import range_of_motion_shares
from data.mesh_io import triangulate, vertex_normals
from models.fit.linearise import RigLinearisation, rodrigues
from models.fit.sequence import check_finite_settings, fit_sequence, initial_state
from models.fit.settings import FitResult, FitSettings
from models.fit.shape import ShapeOffset
from models.rig import HeadNeckModel

MIN_POINTS = 100
# The first frame's search for the head's turn relative to the torso: +-60 degrees of flexion / extension
# (about x), +-75 of axial rotation (y), +-30 of lateral bending (z): the cervical spine's ranges
# (``data.joint_limits``) with a margin.
FIRST_RANGE_DEG = (60.0, 75.0, 30.0)
# Subsample sizes (every k-th, about this many): the neck's and the head's vertices in the search, the scan's
# points in the rigid start and those the head does not explain.  The cost is k-d tree queries.
NECK_VERTICES = 600
RIGID_POINTS = 2000
REST_POINTS = 400
HEAD_VERTICES = 3000


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
    # Every k-th point, about RIGID_POINTS of them: a rigid fit needs few (the tree queries are its cost).
    clouds = [cloud[:: max(1, len(cloud) // RIGID_POINTS)] for cloud in clouds]
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


def part_icp(tree: cKDTree, scan: np.ndarray, part: np.ndarray, normals: np.ndarray, rotation: np.ndarray,
             translation: np.ndarray, iterations: int, keep: float = 0.45) -> tuple[np.ndarray, np.ndarray]:
    """Trimmed point-to-plane ICP of a part of the template (``part`` vertices, their ``normals``) onto the
    scan (``tree`` a cKDTree on ``scan``), model to scan: each vertex to its nearest scan point, the ``keep``
    share of the nearest kept (the part's unseen side has no scan point near it).  Returns the part's
    placement (rotation, translation: template -> scan)."""
    for _ in range(iterations):
        y = part @ rotation.T + translation
        m = normals @ rotation.T
        distance, index = tree.query(y)
        inlier = distance <= np.quantile(distance, keep)
        y, m, p = y[inlier], m[inlier], scan[index[inlier]]
        # Move the part by a small turn w and shift v: minimise sum (m . (y + w x y + v - p))^2.
        step = np.linalg.lstsq(np.concatenate([np.cross(y, m), m], 1), -((y - p) * m).sum(1), rcond=None)[0]
        turn = _turn(step[:3])
        rotation = turn @ rotation
        translation = turn @ translation + step[3:]
    return rotation, translation


def _grid(half_deg: tuple[float, float, float], step_deg: float) -> torch.Tensor:
    """Axis-angle offsets [K,3] (radians) on a grid of ``step_deg`` within +-``half_deg`` per axis."""
    axes = [np.arange(-h, h + 1e-9, step_deg) for h in half_deg]
    return torch.tensor(np.radians(np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)))


def neck_splits() -> list[tuple[torch.Tensor, torch.Tensor]]:
    """The ways a head's turn is shared over C6-C7 ... OC1 that the search tries, each (positive, negative)
    shares [J-1,3] per anatomical axis summing to 1: by the joints' ranges of motion (``data.joint_limits``;
    C1-C2 takes most of the axial turn), and evenly."""
    positive, negative = range_of_motion_shares()
    even = torch.full_like(positive[1:], 1.0 / (len(positive) - 1))
    return [(positive[1:] / positive[1:].sum(0), negative[1:] / negative[1:].sum(0)), (even, even)]


def split_turn(model: HeadNeckModel, turn: torch.Tensor, shares: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """The head's turn relative to the torso, axis-angle [K,3] in the rig's frame, split over C6-C7 ... OC1 by
    ``shares`` (``neck_splits``) -> theta [K,J,3] (bone frames, theta[:, 0] = 0)."""
    positive, negative = shares
    rest = model.anatomical_rest_rotations[1:].double()
    components = torch.einsum("jkc,tk->tjc", rest, turn.double())
    anatomical = components * torch.where(components >= 0, positive.double(), negative.double())
    bones = torch.einsum("jab,tjb->tja", model.anatomical_axes[1:].double(), anatomical)
    return torch.cat([torch.zeros(len(turn), 1, 3, dtype=torch.float64), bones], 1)


class NeckSearch:
    """The neck's bend found by search with the head held where the rigid start put it: candidate turns of
    the head relative to the torso (``split_turn``), each placing the torso so that the head stays, scored by
    the neck's and torso's capped distances to the scan."""

    def __init__(self, model: HeadNeckModel, cap_cm: float = 1.5):
        self.model = model
        self.lin = RigLinearisation(model)
        neck = torch.nonzero(model.skin_weights[:, -1] <= 0.95).flatten()
        self.neck = neck[:: max(1, len(neck) // NECK_VERTICES)]
        template = model.template.double().numpy()
        head = np.flatnonzero(model.skin_weights[:, -1].numpy() > 0.95)
        head = head[:: max(1, len(head) // HEAD_VERTICES)]
        self.head_vertices = template[head]
        self.head_normals = vertex_normals(template, triangulate(model.rig.faces))[head]
        self.cap = cap_cm
        self.splits = neck_splits()

    def place(self, turn: torch.Tensor, split: int, head: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """theta [K,J,3] and the rigid unknowns [K, 6 + 3(J-1)] (reference = identity) of ``turn`` [K,3] shared
        by ``neck_splits()[split]``, with the head at ``head`` [4,4] (template -> capture)."""
        theta = split_turn(self.model, turn, self.splits[split])
        model = self.model
        oc1 = (model.joint_transforms(theta.float()) @ model.rest_world_inverse)[:, -1].double()     # [K,4,4]
        placement = torch.tensor(head) @ torch.linalg.inv(oc1)
        rigid = torch.cat([matrix_to_axis_angle(placement[:, :3, :3]), placement[:, :3, 3],
                           theta[:, 1:].reshape(len(turn), -1)], 1)
        return theta, rigid.float()

    def scores(self, turn: torch.Tensor, split: int, head: np.ndarray, tree: cKDTree,
               rest: np.ndarray) -> np.ndarray:
        """[K] both ways, capped squared distances: the neck's vertices to the scan, and the scan's points that
        the head does not explain (``rest``) to the neck's vertices (else a neck folded onto the face scores
        well)."""
        _, rigid = self.place(turn, split, head)
        k = len(turn)
        q = self.lin.pose(rigid, torch.zeros(k, self.model.num_expressions), torch.zeros(k), torch.ones(k),
                          torch.eye(3).expand(k, 3, 3), vertices=self.neck).double().numpy()
        distance = tree.query(q.reshape(-1, 3))[0].reshape(k, -1)
        out = (np.minimum(distance, self.cap) ** 2).sum(1)
        for c in range(k):
            out[c] += (np.minimum(cKDTree(q[c]).query(rest)[0], self.cap) ** 2).sum()
        return out

    def best(self, centre: torch.Tensor, half_deg, step_deg: float, head: np.ndarray, tree: cKDTree,
             rest: np.ndarray, refinements: int = 2) -> tuple[torch.Tensor, int]:
        """The best turn on a grid about ``centre`` (each split), then on finer grids about the best (its
        split): the turn [3] and the split's index."""
        candidates = centre + _grid(half_deg, step_deg)
        scored = [self.scores(candidates, split, head, tree, rest) for split in range(len(self.splits))]
        split = int(np.argmin([x.min() for x in scored]))
        best = candidates[int(np.argmin(scored[split]))]
        for _ in range(refinements):
            step_deg /= 2
            candidates = best + _grid((step_deg,) * 3, step_deg)
            best = candidates[int(np.argmin(self.scores(candidates, split, head, tree, rest)))]
        return best, split


def searched_start(model: HeadNeckModel, clouds: list[np.ndarray], rotation: torch.Tensor,
                   translation: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per frame the head where the rigid start put it, the neck's bend by ``NeckSearch`` (the first frame
    over the neck's range, each next one near the previous frame's): placement rotation [T,3,3],
    translation [T,3], theta [T,J,3]."""
    search = NeckSearch(model)
    turn = previous = torch.zeros(3, dtype=torch.float64)
    rotations, translations, thetas = [], [], []
    for k, cloud in enumerate(clouds):
        tree = cKDTree(cloud)
        head = np.eye(4)
        head[:3, :3], head[:3, 3] = rotation[k].double().numpy(), translation[k].double().numpy()
        head[:3, :3], head[:3, 3] = part_icp(tree, cloud, search.head_vertices, search.head_normals,
                                             head[:3, :3], head[:3, 3], 20)
        placed_head = search.head_vertices @ head[:3, :3].T + head[:3, 3]
        rest = cloud[cKDTree(placed_head).query(cloud)[0] > search.cap]      # the neck's points (and strays)
        rest = rest[:: max(1, len(rest) // REST_POINTS)]
        if k == 0:
            found, split = search.best(turn, FIRST_RANGE_DEG, 15.0, head, tree, rest)
        else:   # near the constant-velocity prediction from the last two frames
            found, split = search.best(2 * turn - previous if k > 1 else turn, (7.5, 7.5, 7.5), 7.5, head,
                                       tree, rest)
        previous, turn = turn, found
        theta, rigid = search.place(turn[None], split, head)
        rotations.append(rodrigues(rigid[:, :3])[0])
        translations.append(rigid[0, 3:6])
        thetas.append(theta[0].float())
    return torch.stack(rotations), torch.stack(translations), torch.stack(thetas)


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
    rotation, translation, theta = searched_start(model, used, rotation, translation)
    state = initial_state(model, rotation, translation)
    state.rigid[:, 6:] = theta[:, 1:].reshape(len(theta), -1)
    shape = None
    if settings.fit_shape:

        shape = ShapeOffset(model, settings)
    data = ScanData(used, model.rig.faces, settings)
    return fit_sequence(model, data, state, settings, progress, shape)
