"""Characters: same-topology rigs (HACK's template, its own joints), and a procedural giraffe built from any rig.

    python -m scene.characters kind=giraffe [rig=hack_rig.npz] out=giraffe.npz
    python -m scene.characters kind=obj obj=my_giraffe.obj joints=my_bones.json [rig=hack_rig.npz] out=mine.npz

A character is a :class:`data.assets.RigData` (``models.rig.HeadNeckModel`` poses it) with the template's
vertex count, faces and UVs, and its own 8 cervical joint rest frames, skinning weights, expression deltas
and larynx data: theta, psi, tau and eta carry over joint for joint (every mammal has seven cervical
vertebrae; HACK's eight joints c7t1 ... oc1 are the joints between them, T1 and the skull).

- :func:`load_character`: a rig file, ``human`` (the source rig itself), ``giraffe`` (built here), or an
  OBJ with the template's topology plus a joints JSON in the release's ``bones_neutral.json`` layout
  (:func:`character_from_obj`; an artist's own character, as the paper's giraffe).
- :func:`build_giraffe`: the giraffe, from any rig (built-in or the real release).  Every step that moves
  vertices is a global one-to-one map of space (a monotone stretch along one direction, a monotone
  forward stretch of the face, a radial push), so a surface without self-intersections stays without
  them (up to the mesh's linear facets; :func:`self_intersections` checks the result):

  1. muzzle: the face below the eyes moved forward, the cheeks behind it stretched (``muzzle_factor``),
     fading out above the eyes and below the jaw; optional ossicones (two radial bumps on the crown);
  2. neck: a slab of the neck (between T1 and the lowest head vertex, on a slanted level coordinate fitted
     so its level sets separate head from neck) stretched along the rest neck direction, which leans
     forward by ``incline_deg`` from vertical, until the chain T1 -> skull base is ``neck_factor`` times the
     source's; the head and muzzle move with it rigidly (translation only: the face still looks along +z);
  3. joints: the vertebrae re-spaced along the stretched chain with giraffe proportions (C2-C7 of one
     length, the atlas ``atlas_share`` of it); each bone keeps its own axes relative to its anatomical
     frame (turned by the minimal rotation from the source's bone direction to the giraffe's), oc1 keeps
     the head's rest rotation, so the anatomical joint frames of the two rigs agree;
  4. skinning weights recomputed from each vertex's level along the chain (the source's are wrong on a
     stretched neck: HACK binds the neck at C5-C6 level half to the skull): smooth C1 transitions between
     adjacent bones only, so no vertex is bound to a far joint; head vertices are bound to oc1;
  5. expressions (and identity shapes) moved by deformation transfer (:func:`deformation_transfer`,
     Sumner & Popovic 2004), not added raw;
  6. the larynx maps kept in UV space (so on the stretched neck they stretch with it, and tau, in UV
     units, slides the larynx the same share of the neck), the larynx direction turned with the neck's
     inclination and its depth scaled by the square root of the local stretch (``larynx_depth_power``).

Giraffe facts used: seven cervical vertebrae, each over 28 cm long (Swaby, "Giraffe", in Mammal Anatomy:
An Illustrated Guide, Marshall Cavendish 2010, p. 71), together 52-54 % of the vertebral column
(Badlangana, Adams & Manger, Zool. J. Linn. Soc. 155:736-757, 2009, doi:10.1111/j.1096-3642.2008.00458.x),
so of similar lengths: C2-C7 equal here, the atlas (a ring without a long body in mammals) shorter (our
choice).  The proportions are ours, not a scan: the chain T1 -> skull base 5 times the human's (~56 cm
on HACK) under a ~30 cm long head (neck ~2 head lengths; an adult giraffe's is ~3).
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla
import torch
from omegaconf import MISSING

from base.cli import register_config, to_dataclass
from base.errors import InputError, require_file
from data.assets import JOINT_NAMES, RigData, rest_transforms_from_bones
from data.mesh_io import read_obj, triangulate
from models.rig import HeadNeckModel

CHARACTER_NAMES = ("human", "giraffe")
GIRAFFE_TAG = "giraffe"          # RigData.source of a built giraffe starts with it (character_kind)
HEAD_WEIGHT = 0.9                # a source vertex with this much oc1 weight is head
ZERO_DELTA_CM = 1e-5             # a vertex no source shape moves more than this is held fixed in the transfer


# ----------------------------------------------------------------------------- settings


@dataclass
class GiraffeSettings:
    """How :func:`build_giraffe` shapes the giraffe (lengths relative to the source rig).

    neck_factor:    giraffe chain length T1 -> skull base (c7t1 to oc1 origins) over the source's (> 1).
    incline_deg:    forward lean of the rest neck from vertical, degrees.  Our choice, not a measurement:
                    35 (a neck raised ~55 degrees above horizontal, as a standing giraffe is usually seen).
                    Kept at most 40 so each joint's anatomical frame (snapped to the nearest world axes)
                    stays the source's.
    atlas_share:    the atlas (C1, bone c1c2) length over the other vertebrae's (C2-C7 equal).
    muzzle_factor:  the head's front-back depth with the muzzle over the source's (>= 1): the face below
                    the eyes moves forward, the ``muzzle_band_cm`` deep band around the eyes' depth stretches.
    ossicones:      add two ossicones on the crown; ossicone_height: their height over the head's height;
    ossicone_width_deg: their angular radius (Gaussian sigma) seen from the head's centre.
    weight_blend:   skinning transition width at each joint over the shorter adjacent bone (0-1].
    expression_fade_cm: below the head, expression gradients fade to none over this much giraffe neck
                    (see :func:`build_giraffe`).
    larynx_depth_power: the larynx direction's length is multiplied by k ** power, k the neck's local
                    stretch at the larynx (its UV map already makes it k times longer; 0.5: its depth grows
                    as the geometric mean of its new length and unchanged width).
    """

    neck_factor: float = 5.0
    incline_deg: float = 35.0
    atlas_share: float = 0.5
    muzzle_factor: float = 1.5
    muzzle_band_cm: float = 4.0
    ossicones: bool = True
    ossicone_height: float = 0.18
    ossicone_width_deg: float = 9.0
    weight_blend: float = 0.8
    expression_fade_cm: float = 4.0
    larynx_depth_power: float = 0.5

    def __post_init__(self) -> None:
        if not self.neck_factor > 1.0:
            raise ValueError(f"neck_factor={self.neck_factor}: expected > 1 (the giraffe's neck is longer)")
        if not 0.0 <= self.incline_deg <= 40.0:
            raise ValueError(f"incline_deg={self.incline_deg}: expected 0-40 degrees (beyond 45 the neck's "
                             "anatomical frames would snap to other axes)")
        if not 0.1 <= self.atlas_share <= 2.0:
            raise ValueError(f"atlas_share={self.atlas_share}: expected 0.1-2")
        if not self.muzzle_factor >= 1.0:
            raise ValueError(f"muzzle_factor={self.muzzle_factor}: expected >= 1")
        if not 0.0 < self.weight_blend <= 1.0:
            raise ValueError(f"weight_blend={self.weight_blend}: expected in (0, 1]")
        if not self.muzzle_band_cm > 0:
            raise ValueError(f"muzzle_band_cm={self.muzzle_band_cm}: expected > 0")
        if not 0.0 <= self.larynx_depth_power <= 1.0:
            raise ValueError(f"larynx_depth_power={self.larynx_depth_power}: expected 0-1")
        if self.ossicone_height < 0 or self.ossicone_width_deg <= 0 or self.expression_fade_cm <= 0:
            raise ValueError("ossicone_height >= 0, ossicone_width_deg > 0 and expression_fade_cm > 0 expected")


# ----------------------------------------------------------------------------- small helpers


def _smoothstep(x: np.ndarray) -> np.ndarray:
    """0 below 0, 1 above 1, 3x^2 - 2x^3 between (C1)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def _smoothstep_integral(x: np.ndarray) -> np.ndarray:
    """Integral of :func:`_smoothstep` from -inf to x: 0, x^3 - x^4/2, then x - 1/2."""
    inside = np.clip(x, 0.0, 1.0)
    return np.where(x > 1.0, x - 0.5, inside**3 - 0.5 * inside**4)


def _minimal_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3,3] taking unit vector a to unit vector b (Rodrigues)."""
    axis = np.cross(a, b)
    sine, cosine = np.linalg.norm(axis), float(np.dot(a, b))
    if sine < 1e-12:
        return np.eye(3)
    k = axis / sine
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sine * skew + (1 - cosine) * skew @ skew


def rest_world(rig: RigData) -> np.ndarray:
    """Rest world transforms of the bones [J,4,4] (float64) from the L2P chain."""
    world = []
    for j, parent in enumerate(rig.parents):
        local = rig.joint_rest_local[j].astype(np.float64)
        world.append(local if parent < 0 else world[parent] @ local)
    return np.stack(world)


def _local_from_world(world: np.ndarray, parents) -> np.ndarray:
    local = np.empty_like(world)
    for j, parent in enumerate(parents):
        local[j] = world[j] if parent < 0 else np.linalg.inv(world[parent]) @ world[j]
    return local


def _landmark(rig: RigData, names: tuple[str, ...], count: int = 20) -> np.ndarray:
    """Mean rest position [3] of the ``count`` vertices each named expression moves most."""
    points = []
    for name in names:
        if name not in list(rig.expression_names):
            raise InputError(f"rig {rig.source}: no expression '{name}' (needed to find the face's landmarks)")
        k = list(rig.expression_names).index(name)
        magnitude = np.linalg.norm(rig.expression_deltas[k], axis=1)
        points.append(rig.template[np.argsort(magnitude)[-count:]].astype(np.float64))
    return np.concatenate(points).mean(0)


def chain_length(points: np.ndarray) -> float:
    """Length of the polyline through ``points`` [K,3]."""
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


# ----------------------------------------------------------------------------- geometry checks


def _segments_hit_triangles(p: np.ndarray, q: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray,
                            eps: float = 1e-9) -> np.ndarray:
    """[P] segment p->q crosses triangle (a, b, c) (Moller-Trumbore, strictly inside both)."""
    direction = q - p
    e1, e2 = b - a, c - a
    h = np.cross(direction, e2)
    det = np.einsum("ij,ij->i", e1, h)
    ok = np.abs(det) > eps
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = p - a
    u = inv * np.einsum("ij,ij->i", s, h)
    qv = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", direction, qv)
    t = inv * np.einsum("ij,ij->i", e2, qv)
    return ok & (u > eps) & (v > eps) & (u + v < 1 - eps) & (t > eps) & (t < 1 - eps)


def self_intersections(vertices: np.ndarray, faces: np.ndarray, cell: float | None = None,
                       chunk: int = 200_000) -> np.ndarray:
    """Pairs of the mesh's triangles that cross each other: [K,2] triangle indices (of ``triangulate(faces)``).

    Broad phase: triangles binned into a uniform grid by their bounding boxes (cell = the 90th percentile
    of the boxes' extents), candidate pairs from shared cells, then bounding-box overlap.  Narrow phase:
    two triangles cross iff an edge of one passes through the other (each pair tested both ways; a
    coplanar overlap is not counted).  Triangles sharing a vertex are tested only with the edges opposite
    the shared vertex (crossings through it are contact, not intersection); triangles sharing an edge are
    neighbours and skipped.  Quads are split into two triangles (which share an edge).

    Args:
        vertices: [N,3]; faces: [F,3|4].
    Returns:
        [K,2] int64, each pair once (i < j).
    """
    v = np.asarray(vertices, dtype=np.float64)
    tri = triangulate(np.asarray(faces))
    corners = v[tri]                                              # [T,3,3]
    lo, hi = corners.min(1), corners.max(1)
    if cell is None:
        cell = float(np.percentile((hi - lo).max(1), 90)) or 1.0
    origin = lo.min(0)
    first = np.floor((lo - origin) / cell).astype(np.int64)
    last = np.floor((hi - origin) / cell).astype(np.int64)
    span = last - first + 1
    dims = last.max(0) + 1
    # Every (cell, triangle) membership.
    counts = span.prod(1)
    owner = np.repeat(np.arange(len(tri)), counts)
    offset = np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts)
    sy, sz = span[owner, 1], span[owner, 2]
    ix = first[owner, 0] + offset // (sy * sz)
    iy = first[owner, 1] + (offset // sz) % sy
    iz = first[owner, 2] + offset % sz
    key = (ix * dims[1] + iy) * dims[2] + iz
    order = np.argsort(key, kind="stable")
    key, owner = key[order], owner[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    sizes = np.diff(np.r_[starts, len(key)])
    pairs = []
    for size in np.unique(sizes[sizes > 1]):
        groups = starts[sizes == size][:, None] + np.arange(size)[None]   # [G,size] members of each cell
        i, j = np.triu_indices(size, 1)
        pairs.append(np.stack([owner[groups[:, i]].reshape(-1), owner[groups[:, j]].reshape(-1)], 1))
    if not pairs:
        return np.zeros((0, 2), np.int64)
    pairs = np.sort(np.concatenate(pairs), axis=1)
    pairs = np.unique(pairs[pairs[:, 0] != pairs[:, 1]], axis=0)
    overlap = ((lo[pairs[:, 0]] <= hi[pairs[:, 1]]) & (lo[pairs[:, 1]] <= hi[pairs[:, 0]])).all(1)
    pairs = pairs[overlap]
    hits = []
    for start in range(0, len(pairs), chunk):
        block = pairs[start:start + chunk]
        ta, tb = tri[block[:, 0]], tri[block[:, 1]]
        shared = (ta[:, :, None] == tb[:, None, :])               # [P,3,3]
        n_shared = shared.any(2).sum(1)
        hit = np.zeros(len(block), bool)
        for first_tri, second_tri, share_first in ((ta, tb, shared.any(2)), (tb, ta, shared.any(1))):
            a, b, c = (v[second_tri[:, k]] for k in range(3))
            for k in range(3):                                      # edge k: corners k, k+1 of the first
                k2 = (k + 1) % 3
                # skip edges through a shared vertex (contact at that vertex is not a crossing)
                usable = (n_shared == 0) | ((n_shared == 1) & ~share_first[:, k] & ~share_first[:, k2])
                test = usable & ~hit
                if test.any():
                    p, q = v[first_tri[test, k]], v[first_tri[test, k2]]
                    hit[test] |= _segments_hit_triangles(p, q, a[test], b[test], c[test])
        hit &= n_shared < 2
        hits.append(block[hit])
    return np.concatenate(hits) if hits else np.zeros((0, 2), np.int64)


def new_self_intersections(source_vertices: np.ndarray, target_vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Crossing triangle pairs [K,2] of the target that the source (same faces) does not have: what a
    deformation of the source added (HACK's template itself has a few at the lip corners)."""
    own = {tuple(p) for p in self_intersections(source_vertices, faces)}
    pairs = self_intersections(target_vertices, faces)
    keep = np.array([tuple(p) not in own for p in pairs], bool)
    return pairs[keep] if len(pairs) else pairs


# ----------------------------------------------------------------------------- deformation transfer


def _frames(corners: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sumner-Popovic frames V = [v1-v0, v2-v0, n/sqrt|n|] [T,3,3] (columns) and areas [T]."""
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    normal = np.cross(e1, e2)
    norm = np.linalg.norm(normal, axis=1)
    fourth = normal / np.sqrt(np.maximum(norm, 1e-30))[:, None]
    return np.stack([e1, e2, fourth], axis=2), 0.5 * norm


def deformation_transfer(source_rest: np.ndarray, source_deltas: np.ndarray, target_rest: np.ndarray,
                         faces: np.ndarray, gradient_weights: np.ndarray | None = None,
                         fixed: np.ndarray | None = None, pin_weights: np.ndarray | None = None) -> np.ndarray:
    """Move blendshape deltas from a source mesh onto a target of the same topology (Sumner & Popovic,
    "Deformation transfer for triangle meshes", SIGGRAPH 2004).

    Per triangle (quads split in two), the source's deformation gradient Q = V~ V^-1 (V the edge frame
    [v1-v0, v2-v0, n/sqrt|n|] at rest, V~ deformed) is applied to the target's rest edges E; the target's
    deformed vertices x minimise sum_t area_t |[x1-x0, x2-x0] - Q_t E_t|^2 with the ``fixed`` vertices held
    at rest.  One sparse least-squares system (its normal equations factored once, scipy.sparse.linalg.splu)
    solved for every shape and coordinate as right-hand sides.

    Args:
        source_rest: [N,3]; source_deltas: [E,N,3] (cm); target_rest: [N,3]; faces: [F,3|4].
        gradient_weights: [T] in [0,1] per triangle of ``triangulate(faces)`` or None: the source gradient
            is blended towards the identity, Q' = I + w (Q - I) (1 = transfer as is).
        fixed: [N] bool vertices held at rest; default: those no source shape moves more than ZERO_DELTA_CM
            (if there are none, the first vertex, which fixes the translation).
        pin_weights: [N] in [0,1] or None: adds sum_v pin_v * L_vv |x_v - rest_v|^2 (L_vv the vertex's diagonal
            in the normal equations, so a weight of 1 holds a vertex as firmly as its edges do): where the
            gradients are faded, this keeps the region at rest instead of merely undeformed (a long faded
            neck would otherwise swing rigidly with the head's shapes).
    Returns:
        [E,N,3] target deltas (float64).  On a target that is a uniform scaling s of the source they equal
        s * source_deltas (exactly, up to the solver).
    """
    source_rest = np.asarray(source_rest, np.float64)
    target_rest = np.asarray(target_rest, np.float64)
    deltas = np.asarray(source_deltas, np.float64)
    n = len(source_rest)
    tri = triangulate(np.asarray(faces))
    v_rest, _ = _frames(source_rest[tri])
    w_rest, target_area = _frames(target_rest[tri])
    good = (np.abs(np.linalg.det(v_rest)) > 1e-12) & (target_area > 1e-12)
    inverse = np.zeros_like(v_rest)
    inverse[good] = np.linalg.inv(v_rest[good])
    target_edges = w_rest[:, :, :2]                                              # [T,3,2]
    weights = np.ones(len(tri)) if gradient_weights is None else np.clip(np.asarray(gradient_weights), 0, 1)

    if fixed is None:
        fixed = np.linalg.norm(deltas, axis=2).max(0) <= ZERO_DELTA_CM if len(deltas) else np.ones(n, bool)
        if not fixed.any():
            fixed = np.zeros(n, bool)
            fixed[0] = True
    free = np.flatnonzero(~fixed)
    column = np.full(n, -1)
    column[free] = np.arange(len(free))

    # G [2T, N]: rows x_{k} - x_0 (k = 1, 2) of each triangle, scaled by sqrt(area).
    t_index = np.flatnonzero(good)
    scale = np.sqrt(target_area[t_index])
    rows = np.arange(2 * len(t_index))
    g = sp.csr_matrix(
        (np.concatenate([np.repeat(scale, 2), -np.repeat(scale, 2)]),
         (np.concatenate([rows, rows]),
          np.concatenate([tri[t_index][:, 1:].reshape(-1), np.repeat(tri[t_index, 0], 2)]))),
        shape=(len(rows), n))
    g_free = g[:, free].tocsc()
    normal = (g_free.T @ g_free).tocsc()
    if pin_weights is not None:
        pins = np.clip(np.asarray(pin_weights, np.float64)[free], 0.0, 1.0)
        normal = (normal + sp.diags(pins * normal.diagonal())).tocsc()
    solve = spla.splu(normal)

    out = np.zeros_like(deltas)
    for k in range(len(deltas)):
        deformed, _ = _frames((source_rest + deltas[k])[tri])
        gradient = deformed @ inverse                                            # [T,3,3]
        change = weights[:, None, None] * (gradient - np.eye(3))                # Q' - I
        wanted = np.einsum("tij,tjk->tki", change[t_index], target_edges[t_index])  # [T,2,3] edge changes
        rhs = g_free.T @ (scale[:, None, None] * wanted).reshape(-1, 3)          # fixed vertices: zero change
        out[k][free] = solve.solve(np.ascontiguousarray(rhs))
    return out


# ----------------------------------------------------------------------------- skinning along a chain


def chain_weights(level: np.ndarray, joint_levels: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Skinning weights [N,J] from each vertex's level along a chain of J bones.

    Bone j owns the levels between joint j and joint j+1; at each joint j >= 1 (``joint_levels[j]``) the
    weight passes from bone j-1 to bone j over ``widths[j]`` (centred, C1 smoothstep), exactly zero
    beyond; widths narrower than the bones make every vertex bound to at most two adjacent bones.

    Args:
        level: [N] vertex levels; joint_levels: [J] increasing (entry 0 unused); widths: [J] (entry 0 unused).
    Returns:
        [N,J] rows summing to 1.
    """
    j = len(joint_levels)
    above = np.stack([_smoothstep((level - joint_levels[k]) / widths[k] + 0.5) for k in range(1, j)], 1)
    ones, zeros = np.ones((len(level), 1)), np.zeros((len(level), 1))
    return np.concatenate([ones, above], 1) - np.concatenate([above, zeros], 1)


# ----------------------------------------------------------------------------- the giraffe


@dataclass
class GiraffeGeometry:
    """What :func:`giraffe_geometry` derives from a source rig (cm, world frame of the source).

    template: [N,3] the giraffe's rest vertices; level: [N] each vertex's position along the chain
    (arc length from T1); joints: [8,3] joint origins; joint_levels: [8] their arc positions;
    weight_levels: [8] where the skinning passes to each bone; head_start: arc position where the rigid head
    begins; muzzle_shift: [N] forward shift of each vertex by the muzzle (cm); neck_axis: [3] the rest neck
    direction; stretch: [N] local stretch along the neck (1 outside it); slant: the fitted level slant.
    """

    template: np.ndarray
    level: np.ndarray
    joints: np.ndarray
    joint_levels: np.ndarray
    weight_levels: np.ndarray
    head_start: float
    muzzle_shift: np.ndarray
    neck_axis: np.ndarray
    stretch: np.ndarray
    slant: float
    source_chain_cm: float
    chain_cm: float


def _head_maps(rig: RigData, settings: GiraffeSettings, vertices: np.ndarray, head_level: float,
               slant: float, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The muzzle and the ossicones: one-to-one maps of space applied to ``vertices`` [K,3]; returns the
    moved vertices and the muzzle's forward shift [K]."""
    eye = _landmark(rig, ("eyeBlink_L", "eyeBlink_R"))
    chin = _landmark(rig, ("jawOpen",))
    face_height = eye[1] - chin[1]
    x, y, z = vertices.T
    # Muzzle: z' = z + L g(y, z) S((z - z0) / w): the face in front of z0 + w moves forward by L g, the band
    # behind it stretches.  S and g are C1 smoothsteps with dS/dz >= 0 and dg/dz >= 0, so z' is strictly
    # increasing in z for every (x, y): one-to-one.  g fades out above the eyes (on y) and below the jaw
    # (on the slanted neck level, which grows with z).
    depth = vertices[:, 2].max() - vertices[:, 2].min()
    length = (settings.muzzle_factor - 1.0) * depth
    band = settings.muzzle_band_cm
    z0 = eye[2] - 0.5 * band   # centred on the eyes' depth (their height keeps them in place: g ~ 0 there)
    full = eye[1] - 0.4 * face_height
    upper = 1.0 - _smoothstep((y - full) / (eye[1] + 0.5 - full))
    level = (y - origin[1]) + slant * (z - origin[2])
    lower = _smoothstep((level - head_level) / (0.3 * face_height))
    shift = length * upper * lower * _smoothstep((z - z0) / band)
    moved = vertices + np.outer(shift, [0.0, 0.0, 1.0])
    if settings.ossicones and settings.ossicone_height > 0:
        # Radial push r -> r + b(direction) from the head's centre: one-to-one along every ray.
        top = vertices[:, 1].max()
        centre = np.array([0.0, 0.5 * (eye[1] + top), eye[2] - 0.5 * (eye[2] - vertices[:, 2].min())])
        height = settings.ossicone_height * (top - chin[1])
        sigma = np.radians(settings.ossicone_width_deg)
        rel = moved - centre
        radius = np.linalg.norm(rel, axis=1)
        direction = rel / np.maximum(radius, 1e-9)[:, None]
        push = np.zeros(len(moved))
        for side in (1.0, -1.0):
            axis = np.array([0.32 * side, 1.0, -0.25])
            axis /= np.linalg.norm(axis)
            angle = np.arccos(np.clip(direction @ axis, -1.0, 1.0))
            push += height * np.exp(-0.5 * (angle / sigma) ** 2)
        moved = moved + push[:, None] * direction
    return moved, shift


def giraffe_geometry(rig: RigData, settings: GiraffeSettings) -> GiraffeGeometry:
    """The giraffe's rest vertices, joints and chain levels from ``rig`` (see :func:`build_giraffe`)."""
    world = rest_world(rig)
    joints = world[:, :3, 3]
    origin = joints[0]
    template = rig.template.astype(np.float64)
    weights = rig.skin_weights.astype(np.float64)
    head = weights[:, -1] >= HEAD_WEIGHT
    if not head.any() or head.all():
        raise InputError(f"rig {rig.source}: no vertex split into head (oc1 weight >= {HEAD_WEIGHT}) and neck")
    rel = template - origin

    # The slanted level h = dy + s dz whose lowest head vertex is highest: its level sets part head and neck.
    slants = np.linspace(0.0, 1.2, 121)
    lowest = np.array([(rel[head, 1] + s * rel[head, 2]).min() for s in slants])
    slant = float(slants[np.argmax(lowest)])
    head_level = float(lowest.max())
    normal = np.array([0.0, 1.0, slant])
    if head_level <= 1.0:
        raise InputError(f"rig {rig.source}: the head reaches down to T1 (c7t1); no neck to stretch")

    moved, muzzle_shift = _head_maps(rig, settings, template, head_level, slant, origin)

    # Neck slab [lo, hi] on h, smoothstep-edged stretch density, exactly zero outside: D(h) = extra * R(h).
    ramp = 0.15 * head_level
    lo, hi = ramp, head_level - ramp

    def fraction(h: np.ndarray) -> np.ndarray:
        total = hi - lo - ramp
        return ramp * (_smoothstep_integral((h - lo) / ramp) - _smoothstep_integral((h - hi + ramp) / ramp)) / total

    incline = np.radians(settings.incline_deg)
    axis = np.array([0.0, np.cos(incline), np.sin(incline)])

    # The source chain densely sampled, its levels, and the length the giraffe's must have.
    samples = np.concatenate([np.linspace(joints[k], joints[k + 1], 64, endpoint=False) for k in range(len(joints) - 1)]
                             + [joints[-1:]])
    sample_h = (samples - origin) @ normal
    if (np.diff(sample_h) <= 0).any():
        raise InputError(f"rig {rig.source}: the cervical chain does not rise monotonically along the neck level")
    source_length = chain_length(joints)
    target_length = settings.neck_factor * source_length

    # Vertebrae re-spaced along the stretched chain: C7..C2 of one length, the atlas atlas_share of it.
    lengths = np.r_[np.ones(len(JOINT_NAMES) - 2), settings.atlas_share]

    step = target_length * lengths / lengths.sum()          # the bones' lengths (chords)

    def stretched(extra: float):
        """The mapped chain samples, their arc positions, the joints walked along them from T1 at chord
        distances ``step`` (the last one at the chain's end, the skull base), the joints' arc positions,
        and the atlas chord's excess over its length (None where the chain is too short for the walk)."""
        chain = samples + extra * fraction(sample_h)[:, None] * axis
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(chain, axis=0), axis=1))]
        walked, levels, k = [chain[0]], [0.0], 1
        for length in step[:-1]:
            distance = np.linalg.norm(chain[k:] - walked[-1], axis=1)
            ahead = np.flatnonzero(distance >= length)     # first sample at least `length` from the last joint
            if not len(ahead):
                return chain, arc, None, None, None
            k += int(ahead[0])
            a, d = chain[k - 1], chain[k] - chain[k - 1]
            f = a - walked[-1]
            qa, qb, qc = d @ d, 2 * d @ f, f @ f - length**2
            t = (-qb + np.sqrt(max(qb * qb - 4 * qa * qc, 0.0))) / (2 * qa)   # the exact point on that segment
            walked.append(a + t * d)
            levels.append(arc[k - 1] + t * np.sqrt(qa))
        walked.append(chain[-1])
        levels.append(arc[-1])
        excess = float(np.linalg.norm(chain[-1] - walked[-2]) - step[-1])
        return chain, arc, np.stack(walked), np.array(levels), excess

    low, high = 0.0, 10.0 * target_length
    for _ in range(60):  # the longer the stretch, the longer the atlas chord left at the end
        mid = 0.5 * (low + high)
        excess = stretched(mid)[4]
        low, high = (mid, high) if excess is None or excess < 0 else (low, mid)
    extra = 0.5 * (low + high)
    chain, arc, new_joints, joint_levels, _ = stretched(extra)
    if new_joints is None:
        raise InputError(f"rig {rig.source}: could not re-space the vertebrae along the stretched neck")

    h_moved = (moved - origin) @ normal
    giraffe = moved + extra * fraction(h_moved)[:, None] * axis

    # A vertex's level along the chain: the arc position of the chain sample on its h level (slope 1 beyond).
    def level_of(h: np.ndarray) -> np.ndarray:
        inside = np.interp(h, sample_h, arc)
        return inside + np.minimum(h - sample_h[0], 0.0) + np.maximum(h - sample_h[-1], 0.0)

    level = level_of(h_moved)
    density = np.clip((_smoothstep((h_moved - lo) / ramp) - _smoothstep((h_moved - hi + ramp) / ramp)), 0, 1)
    stretch = 1.0 + extra * density / (hi - lo - ramp) * float(axis @ normal)

    head_start = float(level_of(np.array([hi]))[0])
    weight_levels = joint_levels.copy()
    # The head (rigid above the slab) is oc1's; the atlas keeps at least half its length of skin.
    weight_levels[-1] = max(min(joint_levels[-1], head_start), joint_levels[-2] + 0.5 * step[-1])
    return GiraffeGeometry(template=giraffe, level=level, joints=new_joints, joint_levels=joint_levels,
                           weight_levels=weight_levels, head_start=head_start, muzzle_shift=muzzle_shift,
                           neck_axis=axis, stretch=stretch, slant=slant, source_chain_cm=source_length,
                           chain_cm=chain_length(new_joints))


def build_giraffe(rig: RigData, settings: GiraffeSettings | None = None) -> RigData:
    """A giraffe with ``rig``'s topology (vertex count, faces, UVs), its own joints, weights and shapes.

    Steps and the facts behind them: the module docstring.  Expression gradients are faded to the
    identity along the neck below the head (over ``expression_fade_cm`` of giraffe neck) and the neck
    below is pinned at rest: Sumner-Popovic transfer each triangle's gradient as is, and HACK's jawOpen
    also shears the throat (up to ~4 cm at C4-C6 level); on the stretched neck that shear would act on
    edges several times longer and open the neck, not the muzzle, and an unpinned faded neck would swing
    with the jaw.  Identity shapes (built-in rig) transfer unfaded.  Pose correctives, where the
    source has any, are dropped (they were fitted to the human's neck).

    Args:
        rig: the source rig (``RigData``, e.g. ``build_procedural_rig()`` or ``RigData.load(path)``).
        settings: the giraffe's shape (defaults: :class:`GiraffeSettings`).
    Returns:
        The giraffe ``RigData`` (``source`` starts with ``giraffe``; its settings in JSON).
    """
    settings = settings or GiraffeSettings()
    geometry = giraffe_geometry(rig, settings)
    world = rest_world(rig)
    parents = [int(p) for p in rig.parents]

    # Bone frames: each chain bone turned by the minimal rotation from its source direction to the
    # giraffe's; the head (oc1) keeps its rest rotation (the neck only translates it).
    new_world = world.copy()
    old_joints = world[:, :3, 3]
    for j in range(len(parents)):
        if j + 1 < len(parents):
            d_old = old_joints[j + 1] - old_joints[j]
            d_new = geometry.joints[j + 1] - geometry.joints[j]
            turn = _minimal_rotation(d_old / np.linalg.norm(d_old), d_new / np.linalg.norm(d_new))
            new_world[j, :3, :3] = turn @ world[j, :3, :3]
        new_world[j, :3, 3] = geometry.joints[j]
    rest_local = _local_from_world(new_world, parents)

    # Skinning along the chain: transitions over weight_blend of the shorter adjacent bone.
    bone = np.diff(geometry.weight_levels)
    widths = settings.weight_blend * np.r_[0.0, np.minimum(bone[:-1], bone[1:]), bone[-1]]  # oc1: the head is unbounded
    skin = chain_weights(geometry.level, geometry.weight_levels, widths)

    # Expression gradients fade out below the head along the giraffe's neck.
    tri = triangulate(rig.faces)
    def fade(level: np.ndarray) -> np.ndarray:
        return _smoothstep((level - (geometry.head_start - settings.expression_fade_cm)) / settings.expression_fade_cm)

    n_expr = len(rig.expression_deltas)
    expressions = deformation_transfer(rig.template, rig.expression_deltas, geometry.template, rig.faces,
                                       gradient_weights=fade(geometry.level[tri].mean(1)),
                                       pin_weights=1.0 - fade(geometry.level))
    shapes = rig.shape_deltas
    if shapes.size:
        fixed = np.linalg.norm(rig.expression_deltas, axis=2).max(0) <= ZERO_DELTA_CM
        shapes = deformation_transfer(rig.template, rig.shape_deltas, geometry.template, rig.faces,
                                      fixed=fixed if fixed.any() else None)

    # Larynx: maps kept in UV; direction turned with its bone, depth scaled by stretch ** larynx_depth_power.
    model = HeadNeckModel(rig)
    with torch.no_grad():
        offsets = model.larynx_offsets(torch.zeros(1), torch.ones(1))[0].numpy()
    peak = int(np.argmax(np.linalg.norm(offsets, axis=1)))
    larynx_bone = int(np.clip(np.searchsorted(geometry.joint_levels, geometry.level[peak]) - 1, 0, len(parents) - 1))
    turn = new_world[larynx_bone, :3, :3] @ world[larynx_bone, :3, :3].T
    direction = geometry.stretch[peak] ** settings.larynx_depth_power * (turn @ rig.larynx_direction.astype(np.float64))

    record = {"from": rig.source, "settings": dataclasses.asdict(settings),
              "chain_cm": round(geometry.chain_cm, 3), "source_chain_cm": round(geometry.source_chain_cm, 3),
              "slant": geometry.slant, "larynx_stretch": round(float(geometry.stretch[peak]), 3)}
    return RigData(
        template=geometry.template.astype(np.float32),
        faces=rig.faces.copy(),
        vertex_uv=rig.vertex_uv.copy(),
        joint_names=rig.joint_names.copy(),
        parents=rig.parents.copy(),
        joint_rest_local=rest_local,
        skin_weights=skin.astype(np.float32),
        expression_names=rig.expression_names.copy(),
        expression_deltas=expressions[:n_expr].astype(np.float32),
        larynx_maps=rig.larynx_maps.copy(),
        larynx_direction=direction,
        uv_coords=rig.uv_coords.copy(),
        faces_uv=rig.faces_uv.copy(),
        shape_deltas=np.asarray(shapes, np.float32),
        source=f"{GIRAFFE_TAG} " + json.dumps(record, sort_keys=True),
    )


# ----------------------------------------------------------------------------- loading characters


def character_kind(rig: RigData) -> str:
    """``giraffe`` for a rig built by :func:`build_giraffe` (also after saving and loading), else ``human``."""
    return GIRAFFE_TAG if str(rig.source).startswith(GIRAFFE_TAG) else "human"


def _same_topology(base: RigData, vertices: np.ndarray, faces: np.ndarray | None, path: Path) -> None:
    n = len(base.template)
    if len(vertices) != n:
        raise InputError(f"{path}: {len(vertices)} vertices, expected the template's {n} (same topology as the "
                         f"rig {base.source})")
    if faces is not None and len(faces):
        base_tri, tri = triangulate(base.faces), triangulate(faces)
        if base_tri.shape != tri.shape or not np.array_equal(base_tri, tri):
            differ = next((i for i in range(min(len(base_tri), len(tri))) if not np.array_equal(base_tri[i], tri[i])),
                          min(len(base_tri), len(tri)))
            raise InputError(f"{path}: faces differ from the template's (first at triangle {differ + 1} of the "
                             f"fan-split faces; {len(tri)} vs {len(base_tri)} triangles); expected the template's "
                             f"topology")


def read_joints_json(path: str | os.PathLike) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Joint names, parents and rest transforms [J,4,4] from a joints JSON in the release's
    ``bones_neutral.json`` layout (``{name: {matrix, head, length, parent}}``, root to head)."""
    path = require_file(path, "joints")
    try:
        bones = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: malformed JSON ({e}); expected bones in the bones_neutral.json layout") from None
    if not isinstance(bones, dict) or not all(isinstance(b, dict) for b in bones.values()):
        raise InputError(f"{path}: expected an object of bones {{name: {{matrix, head, length, parent}}}} "
                         f"(the release's bones_neutral.json layout)")
    for name, bone in bones.items():
        for key, shape in (("matrix", (3, 3)), ("head", (3,))):
            try:
                value = np.asarray(bone.get(key), dtype=np.float64)
            except (TypeError, ValueError):
                raise InputError(f"{path}: bone '{name}' '{key}' is not numbers, expected {list(shape)}") from None
            if key in bone and value.shape != shape:
                raise InputError(f"{path}: bone '{name}' '{key}' has shape {list(value.shape)}, expected {list(shape)}")
        if "length" in bone and not isinstance(bone["length"], (int, float)):
            raise InputError(f"{path}: bone '{name}' 'length' is not a number")
    return rest_transforms_from_bones(bones, path)


def character_from_obj(obj_path: str | os.PathLike, joints_path: str | os.PathLike, base: RigData) -> RigData:
    """A character from an OBJ with ``base``'s topology and a joints JSON (``bones_neutral.json`` layout).

    The OBJ gives the rest vertices (cm, y up, face +z; same vertex order and faces as ``base``), the JSON
    the joint rest frames.  The skinning weights are ``base``'s (the same vertex is the same point of the
    body), the expression and identity shapes are moved onto the new mesh by :func:`deformation_transfer`,
    the larynx maps and direction are ``base``'s.  Errors name the file.
    """
    obj_path = require_file(obj_path, "obj")
    mesh = read_obj(obj_path)
    _same_topology(base, mesh.vertices, mesh.faces, obj_path)
    names, parents, rest_local = read_joints_json(joints_path)
    if not np.array_equal(parents, base.parents):
        raise InputError(f"{joints_path}: parents {parents.tolist()}, expected {base.parents.tolist()}")
    expressions = deformation_transfer(base.template, base.expression_deltas, mesh.vertices, base.faces)
    shapes = base.shape_deltas
    if shapes.size:
        shapes = deformation_transfer(base.template, shapes, mesh.vertices, base.faces)
    return dataclasses.replace(
        base, template=mesh.vertices.astype(np.float32), joint_names=np.array(names), joint_rest_local=rest_local,
        expression_deltas=expressions.astype(np.float32), shape_deltas=np.asarray(shapes, np.float32),
        pose_correctives=np.zeros((0, 0), np.float32),
        source=f"character {Path(obj_path).resolve()} + {Path(joints_path).resolve()} on {base.source}")


def load_character(spec: str, source: RigData, settings: GiraffeSettings | None = None) -> RigData:
    """The character ``spec`` names: ``human`` (``source`` itself), ``giraffe`` (built from ``source``), or a
    rig / character file (``.npz``).  OBJ characters: :func:`character_from_obj`."""
    if spec == "human":
        return source
    if spec == GIRAFFE_TAG:
        return build_giraffe(source, settings)
    path = Path(spec)
    if path.suffix.lower() == ".obj":
        raise InputError(f"{spec}: an OBJ character needs its joints; make it first with "
                         f"python -m scene.characters kind=obj obj={spec} joints=bones.json out=character.npz")
    if path.suffix.lower() != ".npz" and not path.exists():
        raise InputError(f"character={spec}: expected {' | '.join(CHARACTER_NAMES)} or a character file (.npz)")
    return RigData.load(path)


# ----------------------------------------------------------------------------- command line


@dataclass
class CharactersConfig:
    """``python -m scene.characters`` settings (``configs/characters.yaml``).

    kind: giraffe (built from ``rig``) or obj (``obj`` + ``joints`` on ``rig``'s topology); rig: the source
    rig file (None / builtin: the built-in rig); out: the character file (.npz); check: count the rest
    mesh's self-intersections (and refuse a giraffe that has more than its source); giraffe: the shape.
    """

    kind: str = "giraffe"
    out: str = MISSING
    rig: str | None = None
    obj: str | None = None
    joints: str | None = None
    check: bool = True
    threads: int = 1
    giraffe: GiraffeSettings = field(default_factory=GiraffeSettings)

    def __post_init__(self) -> None:
        if self.kind not in ("giraffe", "obj"):
            raise ValueError(f"kind={self.kind}: expected giraffe or obj")
        if self.kind == "obj" and not (self.obj and self.joints):
            raise ValueError("kind=obj needs obj=<mesh.obj> and joints=<bones.json>")


register_config("characters_schema", CharactersConfig)


def run(cfg) -> RigData:
    """``python -m scene.characters``: build or load the character, check it, save it."""
    settings = to_dataclass(cfg, CharactersConfig, where="scene.characters")
    started = time.perf_counter()
    base = HeadNeckModel.from_config(settings.rig).rig
    if settings.kind == "giraffe":
        character = build_giraffe(base, settings.giraffe)
    else:
        character = character_from_obj(settings.obj, settings.joints, base)
    built = time.perf_counter() - started
    lines = [f"{settings.kind}: {len(character.template)} vertices, {len(character.faces)} faces "
             f"(from {base.source}) in {built:.1f} s"]
    if settings.kind == "giraffe":
        record = json.loads(character.source[len(GIRAFFE_TAG):])
        ratio = record["chain_cm"] / record["source_chain_cm"]
        lines.append(f"neck chain T1 -> skull base {record['chain_cm']:.1f} cm "
                     f"(source {record['source_chain_cm']:.1f} cm, x{ratio:.2f})")
    if settings.check:
        base_hits = len(self_intersections(base.template, base.faces))
        new = new_self_intersections(base.template, character.template, base.faces)
        lines.append(f"self-intersecting triangle pairs at rest: {len(new)} new "
                     f"(the source has {base_hits} of its own)")
        if settings.kind == "giraffe" and len(new):
            raise InputError(f"the giraffe built from {base.source} intersects itself at rest ({len(new)} triangle "
                             "pairs beyond the source's); try a smaller muzzle_factor, ossicone_height or incline_deg")
    character.save(settings.out)
    lines.append(f"wrote {settings.out}")
    print("\n".join(lines))
    return character
