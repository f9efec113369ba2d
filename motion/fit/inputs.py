"""Reading a capture for ``motion.fit``: the frames (OBJ / PLY files in name order, or an ``.npz`` of
``vertices [T,V,3]``), converted to cm, checked against the rig's vertex count (``kind=meshes``) and size.

Bad input raises InputError naming the file (and frame) and what was expected: an empty, NaN or unreadable
file (``data.mesh_io``), a mesh whose vertex count is not the rig's, a capture whose size says the units are
wrong (:func:`check_size`).
"""
from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError
from data.mesh_io import read_points

KINDS = ("meshes", "scans")
UNITS_CM = {"mm": 0.1, "cm": 1.0, "m": 100.0}   # one capture unit in cm
MESH_SUFFIXES = (".obj", ".ply")
# A capture whose extent is outside [1/SIZE_FACTOR, SIZE_FACTOR] times the rig's is in other units (a factor
# of 10 or 100 off); a person differs from the template by far less than 3x, a partial scan (the front half)
# keeps its height and width.
SIZE_FACTOR = 3.0


@dataclass
class Capture:
    """frames: [T,V,3] float32 (kind=meshes) or T arrays [N_t,3] (kind=scans), cm in the capture's frame;
    names: one label per frame (its file, or ``<file>[k]`` for an .npz); source: what was read."""

    frames: np.ndarray | list[np.ndarray]
    names: list[str]
    source: str

    def __len__(self) -> int:
        return len(self.names)


def natural_key(path: Path) -> list:
    """Name order with numbers compared as numbers (``frame_2`` before ``frame_10``)."""
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


def frame_files(folder: Path) -> list[Path]:
    """The OBJ / PLY files in ``folder`` in natural name order; InputError when there are none."""
    files = sorted((p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in MESH_SUFFIXES), key=natural_key)
    if not files:
        raise InputError(f"input={folder}: no .obj or .ply files; expected one mesh or scan per frame")
    return files


def rig_extent_cm(template: np.ndarray) -> float:
    """The rig's size: the diagonal of its template's bounding box (cm)."""
    template = np.asarray(template, dtype=np.float64)
    return float(np.linalg.norm(template.max(0) - template.min(0)))


def capture_extent(points: np.ndarray) -> float:
    """A capture frame's size robust to stray points: the diagonal of the box between the 1st and 99th
    percentiles on each axis."""
    low, high = np.percentile(points, [1.0, 99.0], axis=0)
    return float(np.linalg.norm(high - low))


def check_size(points_cm: np.ndarray, name: str, units: str, rig_cm: float) -> float:
    """The ratio of the frame's extent to the rig's; InputError naming ``name`` and the likely units when it is
    off by more than :data:`SIZE_FACTOR`."""
    extent = capture_extent(points_cm)
    ratio = extent / rig_cm
    if not 1 / SIZE_FACTOR <= ratio <= SIZE_FACTOR:
        raw = extent / UNITS_CM[units]
        likely = min(UNITS_CM, key=lambda u: abs(np.log(raw * UNITS_CM[u] / rig_cm)))
        hint = f"; units={likely}?" if likely != units else ""
        raise InputError(f"{name}: the capture is {extent:.3g} cm across with units={units}, {ratio:.3g}x the rig's "
                         f"{rig_cm:.3g} cm; expected a head and neck about the rig's size{hint}")
    return ratio


def read_npz_vertices(path: Path) -> np.ndarray:
    """``vertices [T,V,3]`` of an .npz; InputError naming the file otherwise."""
    try:
        with np.load(path, allow_pickle=False) as z:
            stored = {k: z[k] for k in z.files}
    except Exception as e:  # numpy and zipfile raise many types for a damaged archive
        raise InputError(f"{path}: not a readable .npz ({type(e).__name__}: {e}); expected vertices [T,V,3]") from None
    if "vertices" not in stored:
        raise InputError(f"{path}: no 'vertices' array (found: {', '.join(sorted(stored)) or 'none'}); "
                         "expected vertices [T,V,3]")
    vertices = stored["vertices"]
    if vertices.ndim != 3 or vertices.shape[2] != 3 or len(vertices) == 0 or not np.issubdtype(vertices.dtype,
                                                                                                 np.number):
        raise InputError(f"{path}: 'vertices' has shape {list(vertices.shape)} ({vertices.dtype}), expected [T,V,3] "
                         "numbers")
    bad = ~np.isfinite(vertices).all(axis=(1, 2))
    if bad.any():
        frame = int(np.argmax(bad))
        vertex = int(np.argmax(~np.isfinite(vertices[frame]).all(axis=1)))
        raise InputError(f"{path}: frame {frame}, vertex {vertex} is not finite")
    return vertices.astype(np.float64)


def read_capture(path: str, kind: str, units: str, rig_template: np.ndarray,
                 progress: Callable[[int], None] | None = None) -> Capture:
    """The capture at ``path`` (a folder of OBJ/PLY frames; or an .npz of ``vertices`` for kind=meshes) in cm,
    every frame checked (vertex count for meshes, size against the rig for both).  ``progress(k)``: frames
    read so far."""
    if kind not in KINDS:
        raise InputError(f"kind={kind}: expected one of {', '.join(KINDS)}")
    if units not in UNITS_CM:
        raise InputError(f"units={units}: expected one of {', '.join(UNITS_CM)}")
    source = Path(path)
    scale, rig_cm, count = UNITS_CM[units], rig_extent_cm(rig_template), len(rig_template)
    if source.is_file() and source.suffix.lower() == ".npz":
        if kind != "meshes":
            raise InputError(f"input={source}: an .npz of vertices [T,V,3] is read with kind=meshes; kind=scans takes "
                             "a folder of PLY / OBJ scans")
        vertices = read_npz_vertices(source) * scale
        if vertices.shape[1] != count:
            raise InputError(f"{source}: {vertices.shape[1]} vertices per frame, the rig has {count}; kind=meshes "
                             "needs the rig's topology (kind=scans fits any)")
        names = [f"{source}[{k}]" for k in range(len(vertices))]
        for k in (0, len(vertices) // 2, len(vertices) - 1):
            check_size(vertices[k], names[k], units, rig_cm)
        if progress is not None:
            progress(len(vertices))
        return Capture(vertices.astype(np.float32), names, str(source))
    if not source.is_dir():
        raise InputError(f"input={source}: not found; expected a folder of OBJ / PLY frames"
                         + (" or an .npz of vertices [T,V,3]" if kind == "meshes" else ""))
    frames, files = [], frame_files(source)
    for k, file in enumerate(files):
        points = read_points(file) * scale
        if kind == "meshes" and len(points) != count:
            raise InputError(f"{file}: {len(points)} vertices, the rig has {count}; kind=meshes needs the rig's "
                             "topology in its vertex order (kind=scans fits any)")
        if kind == "scans" and len(points) < 3:
            raise InputError(f"{file}: {len(points)} point(s); expected a scan")
        check_size(points, str(file), units, rig_cm)
        frames.append(points.astype(np.float32))
        if progress is not None:
            progress(k + 1)
    return Capture(np.stack(frames) if kind == "meshes" else frames, [str(f) for f in files], str(source))
