"""Synthetic captures for the fitting benchmark and tests: raw scans of posed meshes, and another person.

These generators are deliberately *not* the solver's model of the data (``models.fit``): scans are points
sampled on the triangles (not at vertices) with area weighting, seen from one side with a view-dependent
cut, with round holes, Gaussian noise and stray points spread around the head; the other person is the
template reshaped in rig-unaware ways (radial scaling about the neck's axis, a scaled head, a smooth random
field along the normals), which no offset basis of the solver holds exactly.  Units: cm in, cm out.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from data.assets import RigData
from data.mesh_io import triangulate, vertex_normals


@dataclasses.dataclass
class ScanConfig:
    """One frame's scan: ``points`` samples (before the cut, holes and strays) seen from ``view`` (unit,
    the capture's frame: towards the scanner), ``holes`` round holes of ``hole_diameter_cm``, Gaussian
    ``noise_cm`` per axis and ``stray_share`` of stray points in a box ``stray_margin_cm`` around the scan."""

    points: int = 25000
    view: tuple[float, float, float] = (0.0, 0.0, 1.0)
    holes: int = 3
    hole_diameter_cm: float = 3.0
    noise_cm: float = 0.1
    stray_share: float = 0.03
    stray_margin_cm: float = 5.0


def scan_frame(vertices: np.ndarray, tris: np.ndarray, config: ScanConfig, rng: np.random.Generator) -> np.ndarray:
    """A scan [N,3] of one posed mesh: area-weighted samples on the triangles facing the view (the front
    half), minus the holes, plus noise and strays; about ``config.points`` points in all."""
    a, b, c = (vertices[tris[:, k]] for k in range(3))
    cross = np.cross(b - a, c - a)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    facing = cross @ np.asarray(config.view, float) > 0
    prob = np.where(facing, area, 0.0)
    keep_share = 1.0 - config.stray_share
    count = int(round(config.points * keep_share))
    # Oversample for the holes (they remove a few percent), then trim to the count.
    face = rng.choice(len(tris), size=int(count * 1.15) + 16, p=prob / prob.sum())
    u, v = rng.random((2, len(face)))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    points = a[face] + u[:, None] * (b[face] - a[face]) + v[:, None] * (c[face] - a[face])
    centres = points[rng.choice(len(points), size=config.holes, replace=False)]
    for centre in centres:
        points = points[np.linalg.norm(points - centre, axis=1) > config.hole_diameter_cm / 2]
    points = points[rng.permutation(len(points))[:count]]
    points = points + rng.normal(0.0, config.noise_cm, points.shape)
    low = points.min(0) - config.stray_margin_cm
    high = points.max(0) + config.stray_margin_cm
    strays = rng.uniform(low, high, (config.points - len(points), 3))
    out = np.concatenate([points, strays])
    return out[rng.permutation(len(out))].astype(np.float32)


def scan_sequence(vertices: np.ndarray, faces: np.ndarray, seed: int, config: ScanConfig | None = None
                  ) -> list[np.ndarray]:
    """Scans of posed meshes [T,V,3] (cm), one array [N_t,3] per frame, drawn from ``default_rng(seed)``."""
    config = ScanConfig() if config is None else config
    rng = np.random.default_rng(seed)
    tris = triangulate(faces)
    return [scan_frame(frame, tris, config, rng) for frame in np.asarray(vertices, np.float64)]


@dataclasses.dataclass
class PersonConfig:
    """Another person from the template: the neck ``neck_width`` times wider about its vertical axis, the
    head ``head_scale`` times bigger about its centre, plus a smooth random field along the normals of
    ``field_cm`` (std) made of ``field_bumps`` Gaussian bumps of ``field_width_cm``."""

    neck_width: float = 1.08
    head_scale: float = 1.05
    field_cm: float = 0.3
    field_bumps: int = 24
    field_width_cm: float = 5.0


def reshaped_person(rig: RigData, seed: int, config: PersonConfig | None = None) -> RigData:
    """The rig with another person's rest mesh (same skeleton, weights, blendshapes; template changed)."""
    config = PersonConfig() if config is None else config
    rng = np.random.default_rng(seed)
    template = np.asarray(rig.template, np.float64)
    weights = np.asarray(rig.skin_weights, np.float64)
    head = weights[:, -1] + weights[:, -2] * 0.5          # oc1 (and half of c1c2): the head
    neck = np.clip(1.0 - head, 0.0, 1.0)
    head_centre = (head[:, None] * template).sum(0) / head.sum()
    neck_axis = (neck[:, None] * template).sum(0) / neck.sum()
    radial = template - neck_axis
    radial[:, 1] = 0.0                                     # horizontal offsets from the neck's vertical axis
    shape = template + neck[:, None] * (config.neck_width - 1.0) * radial
    shape = shape + head[:, None] * (config.head_scale - 1.0) * (template - head_centre)
    normals = vertex_normals(template, triangulate(rig.faces))
    centres = template[rng.choice(len(template), size=config.field_bumps, replace=False)]
    amplitude = rng.normal(0.0, 1.0, config.field_bumps)
    distance2 = ((template[:, None] - centres[None]) ** 2).sum(-1)
    field = (np.exp(-distance2 / (2 * config.field_width_cm**2)) * amplitude).sum(1)
    field *= config.field_cm / max(field.std(), 1e-12)
    shape = shape + field[:, None] * normals
    return dataclasses.replace(rig, template=shape.astype(rig.template.dtype))
