"""Normal-map rendering of the head-and-neck rig: camera, batched software rasteriser, the larynx point.

Conventions owned here (the tracker ``motion.track`` and the sequence
generator ``scene.normal_sequences`` use them):

- Camera space: x right, y up, z towards the camera (the eye looks along -z).
  Normal maps hold unit normals in camera space; the visible surface has
  n_z > 0.  The default neck view (:func:`neck_camera`) looks at the front of
  the neck from +z in world space, so camera axes equal world axes: image
  right = world +x = the subject's left (as in a photo of a person facing you).
- Images are arrays ``[H,W,...]`` with rows going DOWN and columns right.
  Pixel (col c, row r) has its centre at the continuous image coordinates
  (x = c, y = r); the optical axis passes through ((W-1)/2, (H-1)/2).  A
  point at camera (x, y) lands at ``col = cx + x * s``, ``row = cy - y * s``
  (camera y up, rows down) with ``s = 1 / cm_per_px`` (orthographic) or
  ``s = f / depth``, ``f = distance / cm_per_px`` (perspective; ``cm_per_px``
  is then the scale at the depth of ``centre``).
- depth: cm in front of the eye along the viewing axis (``-z`` in camera
  space); the eye sits ``distance`` cm in front of ``centre`` for both
  projections.  ``inf`` where nothing is rendered.
- Normal maps are encoded and stored as ``data.normals`` says.
- The rig's larynx point (ground truth of the tracker) is
  :func:`larynx_point`: the area-weighted centroid of the posed surface where
  the larynx term exceeds ``LARYNX_CAP`` = 30 % of its maximum, weighted by
  the excess (eta = 1).
- The rig is a :class:`models.rig.HeadNeckModel`, used through its public API only:
  ``rig(theta, psi, tau, eta)``, ``rig.rest_shape``, ``rig.larynx_offsets``, ``rig.faces``,
  ``rig.neutral``.

Public API (other tools build on it): :class:`Camera`, :func:`neck_camera`,
:func:`render_normals` (-> :class:`NormalRender`), :class:`NeckRenderer`
(``renderer(theta, psi, tau, eta)``, ``pose``, ``render_with_truth``),
:func:`larynx_point`, :func:`rest_larynx_point`, :func:`outward_faces`.

Rasterisation: one sample per pixel centre, no antialiasing.  Faces must be
triangles wound counter-clockwise seen from outside (:func:`outward_faces`
fixes a mesh wound the other way); back faces are culled.  Per-triangle pixel
candidates in their bounding boxes, barycentric inside test, z-buffer by
``scatter_reduce('amin')`` on packed (quantised depth, triangle) int64 keys,
then per-pixel interpolation of the area-weighted vertex normals (perspective
correct), renormalised.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from data.mesh_io import triangulate
from models.rig import HeadNeckModel

DEFAULT_SIZE = 256          # pixels, square
DEFAULT_CM_PER_PX = 0.08    # neck view: 256 px = 20.5 cm, the 70 px larynx kernel covers 5.6 cm
DEFAULT_DISTANCE = 50.0     # cm from the eye to the view centre (a webcam-to-neck distance)
NEAR = 1.0                  # cm: triangles with a vertex nearer than this are not drawn

_DEPTH_LEVELS = 2**31 - 1
_EMPTY = torch.iinfo(torch.int64).max


# ----------------------------------------------------------------------------- camera


@dataclass(frozen=True)
class Camera:
    """A pinhole or orthographic camera.

    centre [3]:   world point (cm) on the optical axis, imaged at ((W-1)/2, (H-1)/2).
    rotation [3,3]: world -> camera rotation; its rows are the camera x (right), y (up), z (towards the
                  camera) axes in world coordinates.  Identity: looking at the subject's front from +z.
    width, height: pixels.  cm_per_px: image scale (at the centre's depth for perspective).
    distance:     cm from the eye to ``centre``.  perspective: pinhole if True, else orthographic.
    """

    centre: tuple[float, float, float]
    width: int = DEFAULT_SIZE
    height: int = DEFAULT_SIZE
    cm_per_px: float = DEFAULT_CM_PER_PX
    rotation: tuple = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    distance: float = DEFAULT_DISTANCE
    perspective: bool = False

    @property
    def focal_px(self) -> float:
        """Focal length in pixels of the perspective camera (scale cm_per_px at the centre's depth)."""
        return self.distance / self.cm_per_px

    @property
    def principal_point(self) -> tuple[float, float]:
        """(col, row) of the optical axis."""
        return (self.width - 1) / 2.0, (self.height - 1) / 2.0

    def _rotation(self, like: torch.Tensor) -> torch.Tensor:
        return torch.tensor(self.rotation, dtype=like.dtype, device=like.device)

    def to_camera(self, points: torch.Tensor) -> torch.Tensor:
        """World points [...,3] (cm) -> camera-space points [...,3] relative to the eye."""
        rotation = self._rotation(points)
        centre = torch.tensor(self.centre, dtype=points.dtype, device=points.device)
        relative = (points - centre) @ rotation.T
        return relative - relative.new_tensor([0.0, 0.0, self.distance])

    def project_camera(self, camera_points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Camera-space points [...,3] -> (pixels [...,2] as (col, row), depth [...] cm)."""
        depth = -camera_points[..., 2]
        if self.perspective:
            scale = self.focal_px / depth.clamp_min(1e-6)
        else:
            scale = torch.full_like(depth, 1.0 / self.cm_per_px)
        cx, cy = self.principal_point
        pixels = torch.stack([cx + camera_points[..., 0] * scale, cy - camera_points[..., 1] * scale], dim=-1)
        return pixels, depth

    def project(self, points: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """World points [...,3] (cm) -> (pixels [...,2] as (col, row), depth [...] cm)."""
        return self.project_camera(self.to_camera(points))


# ----------------------------------------------------------------------------- geometry


def face_cross(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """(v1 - v0) x (v2 - v0) of each triangle: vertices [...,N,3], faces [F,3] -> [...,F,3].

    Its direction is the normal of a counter-clockwise triangle, its length twice the triangle's area.
    """
    corners = vertices[..., faces, :]                                                # [...,F,3,3]
    return torch.linalg.cross(corners[..., 1, :] - corners[..., 0, :], corners[..., 2, :] - corners[..., 0, :])


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted vertex normals.  vertices [B,N,3], faces [F,3] (counter-clockwise outside) -> [B,N,3] unit."""
    face_normals = face_cross(vertices, faces)                                       # [B,F,3]
    out = torch.zeros_like(vertices)
    for k in range(3):  # |cross| = 2 * area: summing raw cross products weights faces by area
        out.index_add_(1, faces[:, k], face_normals)
    return out / out.norm(dim=-1, keepdim=True).clamp_min(1e-12)


def outward_faces(vertices: torch.Tensor, faces: np.ndarray | torch.Tensor) -> torch.Tensor:
    """Triangles [F,3] (quads fan-triangulated) wound counter-clockwise seen from outside.

    vertices [N,3].  The winding is flipped when the area-weighted face normals point, on balance,
    towards the mesh's centroid (the mesh may be open, as HACK's neck bottom is).
    """
    triangles = torch.as_tensor(triangulate(np.asarray(faces)), dtype=torch.long)
    vertices = vertices.to(torch.float64)
    outwardness = (face_cross(vertices, triangles) * (vertices[triangles].mean(1) - vertices.mean(0))).sum()
    return triangles if outwardness >= 0 else triangles[:, [0, 2, 1]].contiguous()


def vertex_areas(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """The area around each vertex: a third of its incident triangles' areas.  vertices [N,3], faces [F,3] -> [N]."""
    areas = 0.5 * face_cross(vertices, faces).norm(dim=-1)
    out = vertices.new_zeros(len(vertices))
    for k in range(3):
        out.index_add_(0, faces[:, k], areas / 3.0)
    return out


# The larynx point averages where the larynx term exceeds this fraction of its maximum: the body of the
# larynx, without the map's low fringe, whose footprint changes most as the map slides (measurements:
# benchmarks/README.md, "Tracker and renderer").
LARYNX_CAP = 0.3


def larynx_areas(rig: HeadNeckModel, triangles: torch.Tensor | None = None) -> torch.Tensor:
    """The template's surface area around each vertex [N] (cm^2; :func:`vertex_areas` of the rig's shape
    without a larynx, ``rig.rest_shape(eta=0)``): the constant part of :func:`larynx_point`'s weights,
    computed once per rig.  triangles [F,3]: the rig's faces triangulated (either winding); default:
    triangulated here."""
    if triangles is None:
        triangles = torch.as_tensor(triangulate(rig.faces.numpy()), dtype=torch.long)
    with torch.no_grad():
        template = rig.rest_shape(eta=torch.zeros(1))[0]
    return vertex_areas(template, triangles)


def larynx_point(rig: HeadNeckModel, vertices: torch.Tensor, tau: torch.Tensor, areas: torch.Tensor) -> torch.Tensor:
    """The larynx point [B,3] (cm): the ground-truth position the tracker reports.

    The centroid of the larynx's cap over the posed surface: the vertices ``vertices`` [B,N,3] weighted by
    ``max(|L| - LARYNX_CAP * max|L|, 0)``, |L| the magnitude of the larynx term L(eta = 1, tau) at the
    vertex (``rig.larynx_offsets``, zero away from the larynx), times the vertex's surface area on the
    template (``areas`` [N] = :func:`larynx_areas`).  The area makes it a surface integral (independent of
    how densely the mesh samples the larynx); the cap keeps it on the body of the larynx, away from the
    map's low fringe; eta scales all weights alike, so the point does not depend on it.  vertices posed
    (``rig(theta, psi, tau, eta)``), tau [B] the tau they were posed with.
    """
    magnitude = rig.larynx_offsets(tau, torch.ones_like(tau)).norm(dim=-1)               # [B,N]
    cap = (magnitude - LARYNX_CAP * magnitude.amax(dim=1, keepdim=True)).clamp_min(0.0)
    weights = cap * areas
    return torch.einsum("bn,bnc->bc", weights, vertices) / weights.sum(1, keepdim=True).clamp_min(1e-12)


def rest_larynx_point(rig: HeadNeckModel) -> torch.Tensor:
    """The larynx point [3] at rest (theta 0, psi 0, tau 0, eta 1)."""
    with torch.no_grad():
        tau = torch.zeros(1)
        return larynx_point(rig, rig(rig.neutral(1), tau=tau), tau, larynx_areas(rig))[0]


def neck_camera(rig: HeadNeckModel, size: int = DEFAULT_SIZE, cm_per_px: float = DEFAULT_CM_PER_PX,
                perspective: bool = False, distance: float = DEFAULT_DISTANCE, height: int | None = None) -> Camera:
    """The default neck view: looking at the front of the neck from +z, centred on the rest larynx point."""
    centre = tuple(float(c) for c in rest_larynx_point(rig))
    return Camera(centre=centre, width=int(size), height=int(height or size), cm_per_px=float(cm_per_px),
                  distance=float(distance), perspective=bool(perspective))


# ----------------------------------------------------------------------------- rasteriser


@dataclass
class NormalRender:
    """normals [B,H,W,3] camera-space unit normals (0 where not covered); mask [B,H,W] bool;
    depth [B,H,W] cm in front of the eye (inf where not covered)."""

    normals: torch.Tensor
    mask: torch.Tensor
    depth: torch.Tensor


@dataclass
class Fragments:
    """The visible surface at the covered pixel centres of a batch of ``[B,H,W]`` images.

    pixel [P] flat index into B*H*W; frame [P]; face [P] triangle index; bary [P,3] barycentrics in the
    triangle's corner order (perspective correct); depth [P] cm.
    """

    shape: tuple[int, int, int]
    pixel: torch.Tensor
    frame: torch.Tensor
    face: torch.Tensor
    bary: torch.Tensor
    depth: torch.Tensor

    def dense(self, values: torch.Tensor, fill: float = 0.0) -> torch.Tensor:
        """Scatter per-fragment values [P,...] into images [B,H,W,...] filled with ``fill`` elsewhere."""
        out = values.new_full((self.shape[0] * self.shape[1] * self.shape[2],) + values.shape[1:], fill)
        out[self.pixel] = values
        return out.reshape(self.shape + values.shape[1:])


def rasterize(pixels: torch.Tensor, depth: torch.Tensor, faces: torch.Tensor, height: int, width: int,
              perspective: bool) -> Fragments:
    """The visible triangle and its barycentrics at every covered pixel centre.

    pixels [B,N,2] (col, row), depth [B,N] cm, faces [F,3] counter-clockwise seen from outside.
    """
    batch, num_vertices = pixels.shape[:2]
    num_faces = faces.shape[0]
    dtype = pixels.dtype
    flat_corners = (faces.reshape(1, -1) + num_vertices * torch.arange(batch)[:, None]).reshape(-1)
    corner_xy = pixels.reshape(-1, 2).index_select(0, flat_corners).reshape(batch * num_faces, 3, 2)
    corner_depth = depth.reshape(-1).index_select(0, flat_corners).reshape(batch * num_faces, 3)
    # Depth key, affine in screen space and smaller = nearer: depth (orthographic), -1/depth (perspective).
    corner_key = -1.0 / corner_depth if perspective else corner_depth
    x0, y0 = corner_xy[:, 0, 0], corner_xy[:, 0, 1]
    e1x, e1y = corner_xy[:, 1, 0] - x0, corner_xy[:, 1, 1] - y0
    e2x, e2y = corner_xy[:, 2, 0] - x0, corner_xy[:, 2, 1] - y0
    area2 = e1x * e2y - e1y * e2x
    lo = corner_xy.amin(dim=1)
    hi = corner_xy.amax(dim=1)
    col_lo, row_lo = torch.ceil(lo[:, 0]).clamp_min(0), torch.ceil(lo[:, 1]).clamp_min(0)
    col_hi, row_hi = torch.floor(hi[:, 0]).clamp_max(width - 1), torch.floor(hi[:, 1]).clamp_max(height - 1)
    # Counter-clockwise seen from the camera (x right, y up) is clockwise in (col, row): area2 < 0.
    visible = (area2 < -1e-9) & (col_hi >= col_lo) & (row_hi >= row_lo) & (corner_depth.amin(dim=1) > NEAR)
    kept = visible.nonzero().squeeze(1)                           # [K] flat (frame, face)
    if len(kept) == 0:
        empty = torch.zeros(0, dtype=torch.long)
        return Fragments((batch, height, width), empty, empty, empty, torch.zeros(0, 3, dtype=dtype),
                         torch.zeros(0, dtype=dtype))

    # Affine planes over the screen, a*col + b*row + c, of b1, b2 and the depth key: [B*F,9] -> [K,9].
    inv = 1.0 / torch.where(visible, area2, torch.ones_like(area2))
    b1_a, b1_b = e2y * inv, -e2x * inv
    b2_a, b2_b = -e1y * inv, e1x * inv
    b1_c = -(b1_a * x0 + b1_b * y0)
    b2_c = -(b2_a * x0 + b2_b * y0)
    dk1, dk2 = corner_key[:, 1] - corner_key[:, 0], corner_key[:, 2] - corner_key[:, 0]
    k_a, k_b = b1_a * dk1 + b2_a * dk2, b1_b * dk1 + b2_b * dk2
    k_c = corner_key[:, 0] + b1_c * dk1 + b2_c * dk2
    planes = torch.stack([b1_a, b1_b, b1_c, b2_a, b2_b, b2_c, k_a, k_b, k_c], dim=1).index_select(0, kept)

    # Pixel candidates: every pixel centre in each triangle's clipped bounding box.
    boxes = torch.stack([col_lo, row_lo, col_hi, row_hi], dim=1).index_select(0, kept).long()
    box_w = boxes[:, 2] - boxes[:, 0] + 1
    counts = box_w * (boxes[:, 3] - boxes[:, 1] + 1)
    triangle = torch.repeat_interleave(torch.arange(len(kept)), counts)
    starts = torch.cumsum(counts, 0) - counts
    info = torch.stack([starts, box_w, boxes[:, 0], boxes[:, 1]], dim=1).index_select(0, triangle)
    local = torch.arange(len(triangle)) - info[:, 0]
    row_in_box = torch.div(local, info[:, 1], rounding_mode="floor")
    col = info[:, 2] + local - row_in_box * info[:, 1]
    row = info[:, 3] + row_in_box
    p = planes.index_select(0, triangle)
    colf, rowf = col.to(dtype), row.to(dtype)
    b1 = p[:, 0] * colf + p[:, 1] * rowf + p[:, 2]
    b2 = p[:, 3] * colf + p[:, 4] * rowf + p[:, 5]
    eps = 1e-6
    inside = ((b1 >= -eps) & (b2 >= -eps) & (b1 + b2 <= 1.0 + eps)).nonzero().squeeze(1)
    triangle, col, row = triangle.index_select(0, inside), col.index_select(0, inside), row.index_select(0, inside)
    p = p.index_select(0, inside)
    depth_key = p[:, 6] * colf.index_select(0, inside) + p[:, 7] * rowf.index_select(0, inside) + p[:, 8]

    # z-buffer: min over packed (quantised depth key << 32 | triangle) per pixel.
    lo_key, hi_key = depth_key.min(), depth_key.max()
    span = (hi_key - lo_key).clamp_min(1e-12)
    quantised = ((depth_key - lo_key) / span * _DEPTH_LEVELS).to(torch.int64).clamp(0, _DEPTH_LEVELS)
    frame_of_kept = torch.div(kept, num_faces, rounding_mode="floor")
    pixel = (frame_of_kept.index_select(0, triangle) * height + row) * width + col
    zbuffer = torch.full((batch * height * width,), _EMPTY, dtype=torch.int64)
    zbuffer.scatter_reduce_(0, pixel, (quantised << 32) | triangle, reduce="amin", include_self=True)
    covered = (zbuffer != _EMPTY).nonzero().squeeze(1)
    winner = zbuffer.index_select(0, covered) & 0xFFFFFFFF

    # Per covered pixel: barycentrics at its centre (screen space, then perspective corrected).
    pc = (covered % width).to(dtype)
    pr = (torch.div(covered, width, rounding_mode="floor") % height).to(dtype)
    w = planes.index_select(0, winner)
    s1 = w[:, 0] * pc + w[:, 1] * pr + w[:, 2]
    s2 = w[:, 3] * pc + w[:, 4] * pr + w[:, 5]
    bary = torch.stack([1.0 - s1 - s2, s1, s2], dim=1)
    key_at = w[:, 6] * pc + w[:, 7] * pr + w[:, 8]
    flat_face = kept.index_select(0, winner)
    if perspective:
        weighted = bary / corner_depth.index_select(0, flat_face)
        bary = weighted / weighted.sum(1, keepdim=True)
        pixel_depth = -1.0 / key_at
    else:
        pixel_depth = key_at
    return Fragments((batch, height, width), covered, torch.div(flat_face, num_faces, rounding_mode="floor"),
                     flat_face % num_faces, bary, pixel_depth)


def render_normals(vertices: torch.Tensor, faces: torch.Tensor, camera: Camera, chunk: int = 8) -> NormalRender:
    """Normal maps of meshes.  vertices [B,N,3] world cm; faces [F,3] counter-clockwise outside.

    Returns camera-space normals [B,H,W,3], mask [B,H,W], depth [B,H,W] (see the module conventions).
    Frames go through the rasteriser ``chunk`` at a time (bounded memory).
    """
    vertices = vertices.detach().to(torch.float32)
    faces = torch.as_tensor(faces, dtype=torch.long)
    num_vertices = vertices.shape[1]
    outputs = []
    for start in range(0, vertices.shape[0], chunk):
        cam_points = camera.to_camera(vertices[start:start + chunk])
        normals = vertex_normals(cam_points, faces)        # camera space: the rotation preserves crosses
        pixels, depth = camera.project_camera(cam_points)
        fragments = rasterize(pixels, depth, faces, camera.height, camera.width, camera.perspective)
        corners = (faces.index_select(0, fragments.face) + (fragments.frame * num_vertices)[:, None]).reshape(-1)
        corner_normals = normals.reshape(-1, 3).index_select(0, corners).reshape(-1, 3, 3)
        bary = fragments.bary
        interpolated = (corner_normals[:, 0] * bary[:, 0:1]).addcmul_(corner_normals[:, 1], bary[:, 1:2]) \
            .addcmul_(corner_normals[:, 2], bary[:, 2:3])
        interpolated = interpolated / interpolated.norm(dim=-1, keepdim=True).clamp_min(1e-12)
        outputs.append(NormalRender(fragments.dense(interpolated),
                                    fragments.dense(torch.ones_like(fragments.depth, dtype=torch.bool), False),
                                    fragments.dense(fragments.depth, float("inf"))))
    return NormalRender(*(torch.cat([getattr(o, name) for o in outputs]) for name in ("normals", "mask", "depth")))


# ----------------------------------------------------------------------------- the rig


@dataclass
class NeckRenderer:
    """Normal maps of a rig through a camera (default: :func:`neck_camera`).

    ``renderer(theta [B,J,3], psi=None, tau=None, eta=None) -> NormalRender``; ``pose(...)`` gives the
    posed vertices and the projected :func:`larynx_point` [B,2] (col, row) for the same inputs,
    ``render_with_truth(...)`` both.  The rig's triangles (``faces``, wound outwards) and larynx areas
    (``larynx_areas``) are computed once, here.
    """

    rig: HeadNeckModel
    camera: Camera | None = None
    faces: torch.Tensor = field(init=False)
    larynx_areas: torch.Tensor = field(init=False)

    def __post_init__(self) -> None:
        if self.camera is None:
            self.camera = neck_camera(self.rig)
        with torch.no_grad():
            template = self.rig.rest_shape(eta=torch.zeros(1))[0]
        self.faces = outward_faces(template, self.rig.faces.numpy())
        self.larynx_areas = larynx_areas(self.rig, self.faces)

    @torch.no_grad()
    def pose(self, theta, psi=None, tau=None, eta=None) -> tuple[torch.Tensor, torch.Tensor]:
        """(posed vertices [B,N,3], larynx point pixels [B,2]) for the rig's inputs."""
        tau = theta.new_zeros(theta.shape[0]) if tau is None else tau.to(theta.dtype)
        vertices = self.rig(theta, psi, tau, eta)
        pixels, _ = self.camera.project(larynx_point(self.rig, vertices, tau, self.larynx_areas))
        return vertices, pixels

    @torch.no_grad()
    def __call__(self, theta, psi=None, tau=None, eta=None, chunk: int = 8) -> NormalRender:
        return render_normals(self.rig(theta, psi, tau, eta), self.faces, self.camera, chunk)

    @torch.no_grad()
    def render_with_truth(self, theta, psi=None, tau=None, eta=None, chunk: int = 8):
        """(NormalRender, larynx pixels [B,2]) from one posing."""
        vertices, pixels = self.pose(theta, psi, tau, eta)
        return render_normals(vertices, self.faces, self.camera, chunk), pixels
