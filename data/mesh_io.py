"""Mesh files: fast Wavefront OBJ and PLY readers, OBJ / PLY writers for posed frames.

Faces are ``[F, k]`` vertex indices (0-based), ``k`` = 3 (triangles) or 4
(quads); a mesh mixing the two is written as given and read as triangles.
PLY (:func:`read_ply`): ascii, binary little and big endian; vertices ``x y z``, optional normals
``nx ny nz`` and faces (``vertex_indices`` or ``vertex_index`` lists); a point cloud has no faces
(``[0, 3]``).  Other elements and properties are read past and ignored.  :func:`read_points` reads the
vertices of either format (a scan: a mesh or a point cloud).  Geometry of a mesh: :func:`triangulate` (fan),
:func:`vertex_normals` (area-weighted).
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError, require_file
from base.files import atomic_path
from data.ply import PlyMesh, read_ply


@dataclass
class ObjMesh:
    """vertices [N,3]; faces [F,k] (0-based); uv_coords [M,2]; faces_uv [F,k] or None."""

    vertices: np.ndarray
    faces: np.ndarray
    uv_coords: np.ndarray | None = None
    faces_uv: np.ndarray | None = None


def _numbers(lines: list[bytes], count: int, path: Path, tag: str) -> np.ndarray:
    """Parse lines ``<tag> a b c ...`` into ``[len(lines), count]`` floats (extra columns ignored)."""
    if not lines:
        return np.zeros((0, count))
    rows = [line.split()[1:count + 1] for line in lines]
    if any(len(r) != count for r in rows):
        bad = next(i for i, r in enumerate(rows) if len(r) != count)
        raise InputError(f"{path}: '{tag}' record {bad + 1} has {len(rows[bad])} numbers, expected {count}")
    try:
        return np.array(rows, dtype=np.float64)
    except ValueError:
        raise InputError(f"{path}: a '{tag}' record holds something that is not a number") from None


def read_obj(path: str | os.PathLike, vertices_only: bool = False) -> ObjMesh:
    """Read an OBJ: positions, faces (polygons kept if all have the same size), texture coordinates."""
    path = require_file(path)
    lines = path.read_bytes().splitlines()
    vertices = _numbers([ln for ln in lines if ln.startswith(b"v ")], 3, path, "v")
    if len(vertices) == 0:
        raise InputError(f"{path}: no vertices ('v x y z' lines); expected a Wavefront OBJ mesh")
    if vertices_only:
        return ObjMesh(vertices, np.zeros((0, 3), dtype=np.int64))
    uv = _numbers([ln for ln in lines if ln.startswith(b"vt ")], 2, path, "vt")
    face_lines = [ln.split()[1:] for ln in lines if ln.startswith(b"f ")]
    sizes = {len(f) for f in face_lines}
    if not face_lines:
        raise InputError(f"{path}: no faces ('f' lines); expected a polygon mesh")
    try:
        corners = [[c.split(b"/") for c in f] for f in face_lines]
        if len(sizes) == 1:
            fv = np.array([[int(c[0]) for c in f] for f in corners])
            has_uv = all(len(c) > 1 and c[1] for f in corners for c in f)
            ft = np.array([[int(c[1]) for c in f] for f in corners]) if has_uv else None
        else:  # mixed polygons: fan-triangulate
            tri_v, tri_t = [], []
            for f in corners:
                for i in range(1, len(f) - 1):
                    tri_v.append([int(f[0][0]), int(f[i][0]), int(f[i + 1][0])])
                    if all(len(c) > 1 and c[1] for c in f):
                        tri_t.append([int(f[0][1]), int(f[i][1]), int(f[i + 1][1])])
            fv = np.array(tri_v)
            ft = np.array(tri_t) if len(tri_t) == len(tri_v) else None
    except ValueError:
        raise InputError(f"{path}: an 'f' record holds a non-integer index") from None
    face_label = "'f' record" if len(sizes) == 1 else "triangle (polygons fan-triangulated)"
    fv = _zero_based(fv, len(vertices), path, "vertex", face_label)
    if ft is not None:
        ft = _zero_based(ft, len(uv), path, "texture coordinate", face_label)
    return ObjMesh(vertices, fv, uv if len(uv) else None, ft)


def _zero_based(indices: np.ndarray, count: int, path: Path, what: str, face_label: str) -> np.ndarray:
    """OBJ indices as written [F,k] (1-based; negatives count back from the end) -> 0-based, checked
    against ``count``; the error names the first bad index as written and its face (1-based)."""
    converted = np.where(indices < 0, indices + count + 1, indices) - 1
    bad = (indices == 0) | (converted < 0) | (converted >= count)
    if bad.any():
        face, corner = np.argwhere(bad)[0]
        raise InputError(f"{path}: {face_label} {face + 1} references {what} {indices[face, corner]}, but the file "
                         f"has {count} (OBJ indices run 1..{count}, or -1..-{count} counting back)")
    return converted


def write_obj(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray,
              uv_coords: np.ndarray | None = None, faces_uv: np.ndarray | None = None) -> None:
    """Write one mesh (vertices [N,3], faces [F,k] 0-based, optional UVs) atomically."""
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces)
    parts = ["".join(f"v {x:.6f} {y:.6f} {z:.6f}\n" for x, y, z in vertices)]
    if uv_coords is not None and faces_uv is not None:
        parts.append("".join(f"vt {u:.6f} {v:.6f}\n" for u, v in uv_coords))
        pairs = np.stack([faces + 1, np.asarray(faces_uv) + 1], axis=-1)
        parts.append("".join("f " + " ".join(f"{a}/{b}" for a, b in face) + "\n" for face in pairs))
    else:
        parts.append("".join("f " + " ".join(str(i) for i in face) + "\n" for face in faces + 1))
    with atomic_path(path) as tmp:
        tmp.write_text("".join(parts))


def write_ply(path: str | os.PathLike, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Write a binary little-endian PLY (float32 positions, int32 polygon indices) atomically."""
    vertices = np.ascontiguousarray(vertices, dtype="<f4")
    faces = np.asarray(faces, dtype="<i4")
    header = (
        "ply\nformat binary_little_endian 1.0\n"
        f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
        f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n"
    ).encode("ascii")
    records = np.empty(len(faces), dtype=[("n", "u1"), ("idx", "<i4", (faces.shape[1],))])
    records["n"] = faces.shape[1]
    records["idx"] = faces
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            f.write(header)
            f.write(vertices.tobytes())
            f.write(records.tobytes())


def triangulate(faces: np.ndarray) -> np.ndarray:
    """[F,k] polygons -> [F*(k-2),3] triangles by fanning from the first corner."""
    faces = np.asarray(faces)
    if faces.shape[1] == 3:
        return faces
    return np.concatenate([faces[:, [0, i, i + 1]] for i in range(1, faces.shape[1] - 1)], axis=0)


def vertex_normals(vertices: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """Area-weighted unit vertex normals [V,3] of vertices [V,3] and triangles [F,3]."""
    a, b, c = (vertices[tris[:, k]] for k in range(3))
    face = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices)
    for k in range(3):
        np.add.at(normals, tris[:, k], face)
    return normals / np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)


def read_points(path: str | os.PathLike) -> np.ndarray:
    """The vertices [N,3] (float64) of an OBJ or PLY mesh or point cloud; InputError naming the file when it
    has none, holds a non-finite one, or is of another format."""
    path = require_file(path)
    suffix = path.suffix.lower()
    try:
        if suffix == ".ply":
            vertices = read_ply(path).vertices
        elif suffix == ".obj":
            vertices = read_obj(path, vertices_only=True).vertices
        else:
            vertices = None
    except OSError as e:   # permissions, a device error: the file exists but cannot be read
        raise InputError(f"{path}: cannot be read ({e.strerror or e}); expected a mesh or point cloud") from None
    if suffix == ".obj":
        bad = ~np.isfinite(vertices).all(axis=1)
        if bad.any():
            raise InputError(f"{path}: vertex {int(np.argmax(bad)) + 1} ('v' record) is not finite")
    elif vertices is None:
        raise InputError(f"{path}: a {suffix or 'suffix-less'} file; expected a mesh or point cloud (.obj or .ply)")
    return vertices


__all__ = ["ObjMesh", "PlyMesh", "read_obj", "read_ply", "read_points", "triangulate", "write_obj", "write_ply"]
