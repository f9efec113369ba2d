"""The neck's own image motion at the larynx, from patches of larynx-free skin below and beside it.

Head motion and facial motion (the jaw opening drags the skin of the upper neck down) move the larynx
in the image as much as a swallow does.  The tracker separates the two:

- :class:`NeckPatches` matches small patches of the first frame (below and beside the larynx, where
  the larynx's body does not reach, and one on the chin) in each frame: normalised correlation of
  their low-passed normals within +- ``search_px`` of where they were moved on at their velocity,
  sub-pixel.  A patch below ``min_confidence``, on its window's border, or further than
  ``max_deviation_px`` from the other neck patches' median is left out of that frame, and so is each
  axis along which the correlation peak is flat (second difference below ``min_curvature``: smooth
  skin gives the position no hold).  Their displacements [P,2] are relative to the first frame.
- :class:`NeckModel` maps them to the neck's displacement at the larynx point: a ridge regression
  fitted on the rig (``NeckModel.from_rig``, no rendering: the rig's posed vertices projected), over
  random head poses (up to ``max_deg`` per anatomical axis, shared out over the cervical joints evenly
  for half of them and at random for the others: a nod from the top joints and a bend of the whole neck
  move the patches differently), random
  expressions and tau.  Its features are the patch displacements and their products with the larynx's
  rise (the neck moves more higher up: under flexion the top of the larynx region moves 2.5-4 times as
  far as its bottom); the training patch displacements carry Gaussian noise of ``noise_px`` (1 px: the
  matching's own error under head motion, 0.2-1 px, is mostly the skin's changing look), so the fit
  does not amplify it.  The target is the larynx point's
  displacement between the posed rig and the rig still with the same tau
  (``scene.render.larynx_point``), so the larynx's rise relative to the neck is what remains.

Coordinates: pixels of the frames; offsets relative to the larynx point, rows down.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np
import torch

from motion.track.config import NeckConfig
from motion.track.scores import subpixel_peak
from scene.render import DEFAULT_CM_PER_PX, Camera, NeckRenderer, neck_camera, render_normals

# Patch centres relative to the larynx point at 0.08 cm/px (x right, y down): the lower front of the
# neck beside and below the larynx, as near to it as its body allows (the nearer, the more like the skin
# over the larynx the patch moves: benchmarks/README.md).  Those off the rig's skin (with a margin) or on
# the larynx's body (where the rig with eta FOOTPRINT_ETA and without a larynx differ by more than
# FOOTPRINT_SHARE of the most, at LARYNX_TAUS, widened by a quarter patch) are dropped.
PATCH_CANDIDATES_PX = ((-45.0, 35.0), (45.0, 35.0), (0.0, 60.0), (-30.0, 60.0), (30.0, 60.0), (0.0, 85.0),
                       (-40.0, 85.0), (40.0, 85.0))
# And one on the chin, above the larynx, when the rig's expressions move it (the jaw): the jaw's opening
# drags the skin over the larynx down, which the neck below does not show.  It moves far and fast, so
# it is searched wider (``jaw_search_px``) and not held to the neck patches' median.
JAW_PATCH_PX = (0.0, -66.0)
JAW_MIN_MOTION_CM = 0.5
CANDIDATE_REACH_PX = 100.0       # the view the placement renders reaches this far (and a patch) around the larynx
LARYNX_TAUS = [-0.02, 0.0, 0.02, 0.04, 0.06]
FOOTPRINT_ETA = 1.2
FOOTPRINT_SHARE = 0.3
RISE_SCALE_PX = 20.0             # the rise enters the features in units of 20 px at 0.08 cm/px


@dataclass
class NeckModel:
    """Linear map from patch displacements (and the larynx's rise) to the neck's displacement at the larynx.

    offsets [P,2] patch centres relative to the larynx point (frame pixels), ``free`` [P] bool marking the
    jaw's patch (searched wider, not held to the others' median); features [n,F] and targets
    [n,2] the rig samples it is fitted on (kept to refit without patches that are missing in a frame);
    rise_scale px; rise_range the rises (px) it was fitted over (a rise outside is clipped to it);
    ridge the regularisation.  :meth:`displacement` evaluates it.
    """

    offsets: np.ndarray
    features: np.ndarray
    targets: np.ndarray
    free: np.ndarray | None = None
    rise_scale: float = RISE_SCALE_PX
    rise_range: tuple[float, float] = (-np.inf, np.inf)
    ridge: float = 1e-3
    _weights: dict = field(default_factory=dict, repr=False)

    @property
    def num_patches(self) -> int:
        return len(self.offsets)

    def _features(self, displacement: np.ndarray, rise: np.ndarray) -> np.ndarray:
        """[n,P,2] displacements and [n] rises (px) -> [n,4P+2] features."""
        flat = displacement.reshape(len(displacement), -1)
        r = (rise / self.rise_scale)[:, None]
        return np.concatenate([flat, flat * r, np.ones_like(r), r], axis=1)

    def _columns(self, present: np.ndarray) -> np.ndarray:
        per_axis = np.asarray(present, dtype=bool).reshape(-1)
        return np.concatenate([per_axis, per_axis, [True, True]])

    def weights(self, present: np.ndarray) -> np.ndarray:
        """Ridge weights [F',2] for the patch axes ``present`` [P,2] bool (fitted once per subset)."""
        key = tuple(bool(p) for p in np.asarray(present).reshape(-1))
        if key not in self._weights:
            x = self.features[:, self._columns(np.asarray(key))]
            gram = x.T @ x + self.ridge * len(x) * np.eye(x.shape[1])
            self._weights[key] = np.linalg.solve(gram, x.T @ self.targets)
        return self._weights[key]

    def displacement(self, patches: np.ndarray, present: np.ndarray, rise: float) -> np.ndarray:
        """The neck's displacement [2] (px, relative to the first frame) at the larynx.

        patches [P,2] displacements relative to the first frame; present [P,2] bool, which of them (x, y)
        were measured (others ignored);
        rise the larynx's rise above its first-frame position (px, + = up).  Without patches: zero.
        """
        count = len(self.offsets)
        present = np.broadcast_to(np.asarray(present, dtype=bool).reshape(count, -1), (count, 2))
        if not present.any():
            return np.zeros(2)
        rise = float(np.clip(rise, *self.rise_range))
        w = self.weights(present)
        columns = self._columns(present)
        moved = self._features(np.asarray(patches, np.float64)[None], np.array([rise], np.float64))[0][columns]
        still = self._features(np.zeros((1, self.num_patches, 2)), np.array([rise], np.float64))[0][columns]
        return (moved - still) @ w

    @classmethod
    def from_rig(cls, rig, camera: Camera | None = None, config: NeckConfig | None = None, max_patches: int = 8,
                 samples: int = 1024, max_deg: float = 15.0, expression_share: float = 0.15, noise_px: float = 1.0,
                 seed: int = 0) -> NeckModel:
        """Fit the model on ``rig`` (a ``models.rig.HeadNeckModel``) seen through ``camera`` (default: the
        neck view, ``scene.render.neck_camera``), whose rest larynx point is the offsets' origin.

        The patches (``config.patch_px`` square, at the camera's scale) are the candidates
        ``PATCH_CANDIDATES_PX`` that lie on the rig's skin at rest and off the larynx's body (up to
        ``max_patches``), and ``JAW_PATCH_PX`` on the chin where the rig's expressions move it.

        Args:
            samples: random poses fitted; max_deg: largest head rotation per anatomical axis (degrees), each
                axis's shared out over the joints evenly (half the samples) or by Dirichlet(1) weights;
            expression_share: the chance of each expression being on (weight uniform in [0, 1]);
            noise_px: std of the noise added to the training patch displacements; seed: the samples'.
        Returns:
            the fitted model.
        """
        camera = camera or neck_camera(rig)
        config = config or NeckConfig().at_scale(DEFAULT_CM_PER_PX / camera.cm_per_px)
        factor = DEFAULT_CM_PER_PX / camera.cm_per_px
        wide = _wide(camera, CANDIDATE_REACH_PX * factor + config.patch_px)
        renderer = NeckRenderer(rig, wide)
        offsets, free = _place_patches(rig, renderer, config, max_patches, factor)
        if not len(offsets):
            raise ValueError("no patch of larynx-free skin fits the rig's neck view")
        origin = np.array(wide.principal_point)
        with torch.no_grad():
            vertices_rest = rig(rig.neutral(1))
            rest_view = render_normals(vertices_rest, renderer.faces, wide)
        pixels_rest, depth_rest = (t.numpy() for t in wide.project(vertices_rest[0]))
        skin = []
        for offset in offsets:
            centre = origin + offset
            col, row = np.round(centre).astype(int)
            distance = np.hypot(*(pixels_rest - centre).T)
            distance[np.abs(depth_rest - float(rest_view.depth[0, row, col])) > 0.4] = np.inf   # the visible layer
            nearest = np.argsort(distance)[:4]
            weights = 1.0 / (distance[nearest] + 0.5)
            skin.append((nearest, weights / weights.sum()))
        rng = np.random.default_rng(seed)
        angles = rng.uniform(-1.0, 1.0, (samples, 3)) * np.radians(max_deg)
        shares = rng.dirichlet(np.ones(rig.num_joints), size=(samples, 3)).transpose(0, 2, 1)     # [n,J,3]
        shares[: samples // 2] = 1.0 / rig.num_joints                  # half of them spread evenly
        theta = angles[:, None, :] * shares
        psi = rng.uniform(0.0, 1.0, (samples, rig.num_expressions))
        psi *= rng.uniform(size=psi.shape) < expression_share
        tau = rng.uniform(-0.02, 0.06, samples)
        moved, target, rise = [], [], []
        with torch.no_grad():
            for start in range(0, samples, 256):
                part = slice(start, start + 256)
                theta_t = rig.from_anatomical(torch.tensor(theta[part], dtype=torch.float32))
                psi_t = torch.tensor(psi[part], dtype=torch.float32)
                tau_t = torch.tensor(tau[part], dtype=torch.float32)
                vertices, larynx = renderer.pose(theta_t, psi_t, tau_t)
                _, still = renderer.pose(torch.zeros_like(theta_t), None, tau_t)
                pixels = wide.project(vertices)[0].numpy()
                moved.append(np.stack([(w[None, :, None] * (pixels[:, idx] - pixels_rest[idx])).sum(1)
                                       for idx, w in skin], axis=1))
                target.append((larynx - still).numpy())
                rise.append(origin[1] - still[:, 1].numpy())
        moved = np.concatenate(moved) + rng.normal(0.0, noise_px * factor, (samples, len(skin), 2))
        rise = np.concatenate(rise)
        model = cls(offsets, np.zeros((0, 0)), np.concatenate(target).astype(np.float64), free,
                    factor * RISE_SCALE_PX, (float(rise.min()), float(rise.max())))
        model.features = model._features(moved, rise)
        return model


def _place_patches(rig, renderer: NeckRenderer, config: NeckConfig, max_patches: int,
                   factor: float) -> tuple[np.ndarray, np.ndarray]:
    """(patch offsets [P,2] from the larynx point, pixels of ``renderer.camera``; free [P] bool): the
    candidates ``PATCH_CANDIDATES_PX`` (scaled by ``factor``) whose square lies on the skin at rest and
    clear of the larynx's footprint (see ``NeckModel.from_rig``), and the jaw's patch ``JAW_PATCH_PX``
    where it lies on the skin and the rig's expressions move it by ``JAW_MIN_MOTION_CM`` or more."""
    camera = renderer.camera
    taus = torch.tensor(LARYNX_TAUS * 2)
    etas = torch.tensor([FOOTPRINT_ETA] * len(LARYNX_TAUS) + [0.0] * len(LARYNX_TAUS))
    view = renderer(rig.neutral(len(taus)), tau=taus, eta=etas)
    normals = view.normals.numpy()
    half = len(LARYNX_TAUS)
    change = np.linalg.norm(normals[:half] - normals[half:], axis=-1).max(0)
    footprint = (change > FOOTPRINT_SHARE * change.max()).astype(np.uint8)
    half_patch = config.patch_px // 2
    footprint = cv2.dilate(footprint, np.ones((half_patch + 1,) * 2, np.uint8)) > 0
    skin = cv2.erode(view.mask[half].numpy().astype(np.uint8), np.ones((2 * half_patch + 5,) * 2, np.uint8)) > 0
    origin = np.array(camera.principal_point)

    def usable(offset) -> bool:
        col, row = np.round(origin + offset).astype(int)
        return bool(0 <= row < camera.height and 0 <= col < camera.width and skin[row, col] and not footprint[row, col])

    chosen = [o for o in np.asarray(PATCH_CANDIDATES_PX, np.float64) * factor if usable(o)][:max_patches]
    free = [False] * len(chosen)
    jaw = np.asarray(JAW_PATCH_PX, np.float64) * factor
    if rig.num_expressions and usable(jaw):
        with torch.no_grad():
            pixels = camera.project(rig(rig.neutral(1))[0])[0].numpy()
        near = np.argsort(np.hypot(*(pixels - (origin + jaw)).T))[:4]
        if float(rig.expression_deltas[:, near].norm(dim=-1).amax()) >= JAW_MIN_MOTION_CM:
            chosen.append(jaw)
            free.append(True)
    return np.array(chosen, dtype=np.float64).reshape(-1, 2), np.array(free, dtype=bool)


def _wide(camera: Camera, reach: float) -> Camera:
    """The camera widened to hold ``reach`` pixels around its centre."""
    size = max(camera.width, camera.height, 2 * int(np.ceil(reach)) + 1)
    return Camera(camera.centre, size, size, camera.cm_per_px, camera.rotation, camera.distance, camera.perspective)


@dataclass
class NeckPatches:
    """Patches of the first frame, matched in each later frame (see the module doc).

    ``NeckPatches(frame [H,W,3], larynx (x, y), offsets [P,2], config, free [P] bool or None)``;
    ``measure(frame)`` -> (displacements [P,2] px relative to the first frame, present [P,2] bool: which
    axes were measured).
    """

    frame: np.ndarray
    larynx: tuple[float, float]
    offsets: np.ndarray
    config: NeckConfig
    free: np.ndarray | None = None
    centres: np.ndarray = field(init=False)
    references: list = field(init=False)
    last: np.ndarray = field(init=False)
    velocity: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        half = self.config.patch_px // 2
        h, w = self.frame.shape[:2]
        self.centres = np.round(np.asarray(self.larynx) + np.asarray(self.offsets)).astype(int)
        self.references = []
        for col, row in self.centres:
            region = self._lowpassed(self.frame, col, row, half)
            ok = region is not None and bool((np.abs(region[1]).sum(-1) > 0).all())
            self.references.append(np.ascontiguousarray(region[1]) if ok else None)
        self.last = np.zeros((len(self.centres), 2))
        self.velocity = np.zeros((len(self.centres), 2))      # px per frame, from the last two matches
        self.free = np.zeros(len(self.centres), bool) if self.free is None else np.asarray(self.free, bool)
        self.frame = None  # not kept: the references hold what is needed

    def _lowpassed(self, frame: np.ndarray, col: int, row: int, half: int, reach: int = 0):
        """((x0, y0), the low-passed square of half-size ``half + reach`` around (col, row), cut to the frame)
        or None when not even the patch (half-size ``half``) fits; the blur sees its context."""
        h, w = frame.shape[:2]
        sigma = self.config.lowpass_sigma_px
        pad = int(np.ceil(2 * sigma)) if sigma > 0 else 0       # the Gaussian cut at 2 sigma
        if col - half < 0 or row - half < 0 or col + half + 1 > w or row + half + 1 > h:
            return None
        x0, y0 = max(0, col - half - reach), max(0, row - half - reach)
        x1, y1 = min(w, col + half + reach + 1), min(h, row + half + reach + 1)
        xa, ya, xb, yb = max(0, x0 - pad), max(0, y0 - pad), min(w, x1 + pad), min(h, y1 + pad)
        region = frame[ya:yb, xa:xb]
        if sigma > 0:
            region = cv2.GaussianBlur(region, (2 * pad + 1,) * 2, sigma, borderType=cv2.BORDER_REFLECT)
        return (x0, y0), region[y0 - ya:y1 - ya, x0 - xa:x1 - xa]

    def _blurred(self, frame: np.ndarray, x0: int, y0: int, x1: int, y1: int) -> np.ndarray:
        """The frame's low-passed box [y0:y1, x0:x1] (the blur sees its context)."""
        h, w = frame.shape[:2]
        sigma = self.config.lowpass_sigma_px
        if sigma <= 0:
            return frame[y0:y1, x0:x1]
        pad = int(np.ceil(2 * sigma))
        xa, ya, xb, yb = max(0, x0 - pad), max(0, y0 - pad), min(w, x1 + pad), min(h, y1 + pad)
        region = cv2.GaussianBlur(frame[ya:yb, xa:xb], (2 * pad + 1,) * 2, sigma, borderType=cv2.BORDER_REFLECT)
        return region[y0 - ya:y1 - ya, x0 - xa:x1 - xa]

    def measure(self, frame: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        half = self.config.patch_px // 2
        h, w = frame.shape[:2]
        out = self.last.copy()
        present = np.zeros((len(self.centres), 2), dtype=bool)
        boxes: list = [None] * len(self.centres)
        for i, (col, row) in enumerate(self.centres):
            if self.references[i] is None:
                continue
            reach = self.config.jaw_search_px if self.free[i] else self.config.search_px
            gx, gy = np.round(self.last[i] + self.velocity[i]).astype(int) + (col, row)
            if gx - half < 0 or gy - half < 0 or gx + half + 1 > w or gy + half + 1 > h:
                continue                                        # the patch has left the frame
            boxes[i] = (max(0, gx - half - reach), max(0, gy - half - reach),
                        min(w, gx + half + reach + 1), min(h, gy + half + reach + 1))
        sharpness = self.config.min_curvature
        for group in (~self.free, self.free):                   # one low-pass for the neck's patches, one for the jaw's
            members = [i for i in np.flatnonzero(group) if boxes[i] is not None]
            if not members:
                continue
            bx0, by0 = min(boxes[i][0] for i in members), min(boxes[i][1] for i in members)
            bx1, by1 = max(boxes[i][2] for i in members), max(boxes[i][3] for i in members)
            region = self._blurred(frame, bx0, by0, bx1, by1)
            for i in members:
                x0, y0, x1, y1 = boxes[i]
                window = np.ascontiguousarray(region[y0 - by0:y1 - by0, x0 - bx0:x1 - bx0])
                scores = cv2.matchTemplate(window, self.references[i], cv2.TM_CCOEFF_NORMED)
                _, peak, _, (c, r) = cv2.minMaxLoc(scores)
                if peak < self.config.min_confidence:
                    continue
                sx, sy = subpixel_peak(scores, c, r)
                found = (x0 + sx + half - self.centres[i][0], y0 + sy + half - self.centres[i][1])
                if not (0 < c < scores.shape[1] - 1 and 0 < r < scores.shape[0] - 1):
                    out[i] = found          # on the window's border it may lie beyond: searched from there next
                    continue
                # Along an axis where the peak is flat (smooth skin) the position is not measured (and kept).
                present[i] = (2 * peak - scores[r, c - 1] - scores[r, c + 1] >= sharpness,
                              2 * peak - scores[r - 1, c] - scores[r + 1, c] >= sharpness)
                out[i] = np.where(present[i], found, out[i])
        neck = present & ~self.free[:, None]
        for axis in (0, 1):
            if neck[:, axis].any():
                # A patch far from the others' median has lost its skin (a fold, the mesh's edge): it is left
                # out, and, like a patch that did not match, searched around the others' median next time.
                median = np.median(out[neck[:, axis], axis])
                kept = neck[:, axis] & (np.abs(out[:, axis] - median) <= self.config.max_deviation_px)
                lost = ~self.free & ~kept
                out[lost, axis] = np.median(out[kept, axis]) if kept.any() else median
                present[~self.free, axis] = kept[~self.free]
        self.velocity = np.where(present, out - self.last, 0.0)
        self.last = out
        return out, present
