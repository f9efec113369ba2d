"""Self-intersection checks of a triangle mesh: which triangle pairs cross, and which a deformation added."""
from __future__ import annotations

import numpy as np

from data.mesh_io import triangulate


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
