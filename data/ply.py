"""The PLY reader (``data.mesh_io.read_ply``): ascii, binary little and big endian.

The format (Turk, "The PLY polygon file format", 1994; the header names elements and their typed
properties, then the body holds each element's records in the header's order): ``ply``, a ``format``
line, ``comment`` / ``obj_info`` lines, ``element <name> <count>`` each followed by its
``property <type> <name>`` or ``property list <count type> <item type> <name>`` lines, ``end_header``.
Types: char/int8, uchar/uint8, short/int16, ushort/uint16, int/int32, uint/uint32, float/float32,
double/float64.

Read: the ``vertex`` element's ``x y z`` (required) and ``nx ny nz`` (optional, all three), the ``face``
element's ``vertex_indices`` (or ``vertex_index``) list; faces of mixed sizes are fan-triangulated.  Other
elements and properties are read past.  Malformed input raises InputError naming the file and the line
(ascii; lines counted from 1 in the whole file) or the byte offset (binary) and what was expected.
"""
from __future__ import annotations

import os
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError, require_file

TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
         "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
         "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
FORMATS = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}
FACE_LISTS = ("vertex_indices", "vertex_index")


@dataclass
class PlyMesh:
    """vertices [N,3] float64; faces [F,k] int64 0-based ([0,3] for a point cloud); normals [N,3] or None."""

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray | None = None


@dataclass
class _Property:
    name: str
    type: str                  # numpy type code without byte order, e.g. "f4"
    count_type: str | None = None   # set for a list property


@dataclass
class _Element:
    name: str
    count: int
    properties: list[_Property]
    line: int  # the header line declaring it


def _parse_header(data: bytes, path: Path) -> tuple[str, list[_Element], int, int]:
    """(format, elements, byte offset of the body, number of header lines)."""
    end = data.find(b"end_header")
    if not data.startswith(b"ply"):
        raise InputError(f"{path}: does not start with 'ply'; expected a PLY file")
    if end < 0:
        raise InputError(f"{path}: no 'end_header' line; expected a PLY header ending with it")
    stop = data.find(b"\n", end)
    body = len(data) if stop < 0 else stop + 1
    lines = data[:body].decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []
    for number, line in enumerate(lines, start=1):
        words = line.split()
        if not words or words[0] in ("ply", "comment", "obj_info", "end_header"):
            continue
        where = f"{path}: header line {number}"
        if words[0] == "format":
            if len(words) < 2 or words[1] not in FORMATS:
                raise InputError(f"{where}: format '{' '.join(words[1:])}', expected one of {', '.join(FORMATS)}")
            fmt = words[1]
        elif words[0] == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise InputError(f"{where}: '{line.strip()}', expected 'element <name> <count>'")
            elements.append(_Element(words[1], int(words[2]), [], number))
        elif words[0] == "property":
            if not elements:
                raise InputError(f"{where}: a property before any element")
            if words[1:2] == ["list"]:
                if len(words) != 5 or words[2] not in TYPES or words[3] not in TYPES:
                    raise InputError(f"{where}: '{line.strip()}', expected 'property list <count type> "
                                     f"<item type> <name>' with types among {', '.join(TYPES)}")
                elements[-1].properties.append(_Property(words[4], TYPES[words[3]], TYPES[words[2]]))
            else:
                if len(words) != 3 or words[1] not in TYPES:
                    raise InputError(f"{where}: '{line.strip()}', expected 'property <type> <name>' with a type "
                                     f"among {', '.join(TYPES)}")
                elements[-1].properties.append(_Property(words[2], TYPES[words[1]]))
        else:
            raise InputError(f"{where}: unknown header keyword '{words[0]}'")
    if fmt is None:
        raise InputError(f"{path}: no 'format' line in the header; expected ascii, binary_little_endian or "
                         "binary_big_endian")
    return fmt, elements, body, len(lines)


def _read_ascii(data: bytes, path: Path, elements: list[_Element], body: int, first_line: int) -> tuple[dict, dict]:
    """({element name: per-property arrays}, {element name: record index -> " (line n)"}) from the ascii
    body, one record per line."""
    lines = [ln for ln in enumerate(data[body:].splitlines(), start=first_line) if ln[1].strip()]
    out, locate, at = {}, {}, 0
    for element in elements:
        records = lines[at:at + element.count]
        if len(records) < element.count:
            raise InputError(f"{path}: the file ends after {len(records)} of the {element.count} '{element.name}' "
                             f"records (declared on header line {element.line})")
        at += element.count
        numbers = [n for n, _ in records]
        locate[element.name] = lambda i, numbers=numbers: f" (line {numbers[i]})"
        if not any(p.count_type for p in element.properties):
            width = len(element.properties)
            table = _fast_table(records, width)
            if table is not None:
                out[element.name] = {p.name: table[:, k] for k, p in enumerate(element.properties)}
                continue
            rows = [r.split() for _, r in records]
            bad = next((i for i, r in enumerate(rows) if len(r) != width), None)
            if bad is not None:
                raise InputError(f"{path}: line {records[bad][0]}: {len(rows[bad])} numbers, expected {width} "
                                 f"('{element.name}' record {bad + 1})")
            try:
                table = np.array(rows, dtype=np.float64).reshape(len(rows), width)
            except ValueError:
                bad = next(i for i, r in enumerate(rows) if not _all_numbers(r))
                raise InputError(f"{path}: line {records[bad][0]}: not a number in '{element.name}' record "
                                 f"{bad + 1}") from None
            out[element.name] = {p.name: table[:, k] for k, p in enumerate(element.properties)}
            continue
        columns = {p.name: [] for p in element.properties}
        for index, (number, record) in enumerate(records):
            words, pos = record.split(), 0
            try:
                for prop in element.properties:
                    if prop.count_type:
                        n = int(words[pos])
                        if len(words) < pos + 1 + n:
                            raise IndexError
                        columns[prop.name].append([float(w) for w in words[pos + 1:pos + 1 + n]])
                        pos += 1 + n
                    else:
                        columns[prop.name].append(float(words[pos]))
                        pos += 1
            except (IndexError, ValueError):
                raise InputError(f"{path}: line {number}: '{element.name}' record {index + 1} is malformed (too "
                                 f"few numbers for its properties or a list's count, or not a number)") from None
            if pos != len(words):
                raise InputError(f"{path}: line {number}: '{element.name}' record {index + 1} has {len(words)} "
                                 f"numbers, its properties take {pos}")
        out[element.name] = columns
    return out, locate


def _fast_table(records: list[tuple[int, bytes]], width: int) -> np.ndarray | None:
    """The records as a [N, width] table parsed in one go (numpy's text parser, twice as fast as per line), or
    None when the count of numbers is off or a token is not a number (the caller then finds the line)."""
    text = b" ".join(r for _, r in records).decode("ascii", errors="replace")
    with warnings.catch_warnings():
        warnings.simplefilter("error")   # numpy warns (and stops) at a token that is not a number
        try:
            values = np.fromstring(text, dtype=np.float64, sep=" ")
        except (ValueError, DeprecationWarning):
            return None
    if values.size != len(records) * width or any(len(r.split()) != width for _, r in records):
        return None
    return values.reshape(len(records), width)


def _all_numbers(words: list[bytes]) -> bool:
    try:
        [float(w) for w in words]
    except ValueError:
        return False
    return True


def _read_binary(data: bytes, path: Path, elements: list[_Element], body: int, order: str) -> tuple[dict, dict]:
    """({element name: per-property arrays (lists of arrays for list properties)}, {element name: record
    index -> " (byte n)", where records have one size}) from the binary body."""
    out, locate, at = {}, {}, body
    for element in elements:
        start = at
        props = element.properties
        if not any(p.count_type for p in props):
            dtype = np.dtype([(f"p{k}", order + p.type) for k, p in enumerate(props)])
            size = dtype.itemsize * element.count
            if at + size > len(data):
                _truncated(path, element, at, dtype.itemsize, len(data))
            table = np.frombuffer(data, dtype=dtype, count=element.count, offset=at)
            out[element.name] = {p.name: table[f"p{k}"].astype(np.float64) for k, p in enumerate(props)}
            locate[element.name] = lambda i, start=start, size=dtype.itemsize: f" (byte {start + i * size})"
            at += size
            continue
        out[element.name], at = _binary_lists(data, path, element, at, order)
        count = max(element.count, 1)
        size = (at - start) // count
        if size * count == at - start:  # one record size: a record's byte offset is known
            locate[element.name] = lambda i, start=start, size=size: f" (byte {start + i * size})"
        else:
            locate[element.name] = lambda i: ""
    return out, locate


def _truncated(path: Path, element: _Element, start: int, record_bytes: int, total: int) -> None:
    whole = (total - start) // record_bytes if record_bytes else 0
    raise InputError(f"{path}: the file ends at byte {total} inside '{element.name}' record {whole + 1} of "
                     f"{element.count} (the element starts at byte {start}, {record_bytes} bytes a record); "
                     "expected the whole element: a truncated file?")


def _binary_lists(data: bytes, path: Path, element: _Element, at: int, order: str) -> tuple[dict, int]:
    """An element with list properties.  Fast path: every list has the first record's length (a mesh of
    triangles or quads), checked; otherwise record by record."""
    props, start = element.properties, at
    if element.count == 0:
        return {p.name: [] for p in props}, at
    fields, pos = [], at
    for k, p in enumerate(props):
        if p.count_type:
            count_dtype = np.dtype(order + p.count_type)
            if pos + count_dtype.itemsize > len(data):
                _truncated(path, element, start, 1, len(data))
            n = int(np.frombuffer(data, count_dtype, count=1, offset=pos)[0])
            fields += [(f"n{k}", count_dtype), (f"p{k}", order + p.type, (n,))]
            pos += count_dtype.itemsize + n * np.dtype(p.type).itemsize
        else:
            fields.append((f"p{k}", order + p.type))
            pos += np.dtype(p.type).itemsize
    dtype = np.dtype(fields)
    if at + dtype.itemsize * element.count <= len(data):
        table = np.frombuffer(data, dtype=dtype, count=element.count, offset=at)
        counts = [table[f"n{k}"] for k, p in enumerate(props) if p.count_type]
        if all((c == c[0]).all() for c in counts):
            return ({p.name: table[f"p{k}"].astype(np.float64) for k, p in enumerate(props)},
                    at + dtype.itemsize * element.count)
    columns = {p.name: [] for p in props}  # mixed list lengths: record by record
    for index in range(element.count):
        record_start = at
        for p in props:
            count_dtype = np.dtype(order + (p.count_type or p.type))
            if at + count_dtype.itemsize > len(data):
                raise InputError(f"{path}: the file ends at byte {len(data)} inside '{element.name}' record "
                                 f"{index + 1} of {element.count} (it starts at byte {record_start}); "
                                 "a truncated file?")
            value = np.frombuffer(data, count_dtype, count=1, offset=at)[0]
            at += count_dtype.itemsize
            if p.count_type is None:
                columns[p.name].append(float(value))
                continue
            item = np.dtype(order + p.type)
            n = int(value)
            if at + n * item.itemsize > len(data):
                raise InputError(f"{path}: byte {at - count_dtype.itemsize}: '{element.name}' record {index + 1} "
                                 f"lists {n} items, but the file ends at byte {len(data)}; a truncated file?")
            columns[p.name].append(np.frombuffer(data, item, count=n, offset=at).astype(np.float64))
            at += n * item.itemsize
    return columns, at


def _faces(lists, path: Path, vertex_count: int, located) -> np.ndarray:
    """Face index lists -> [F,k] int64 (mixed sizes fan-triangulated), checked against the vertices."""
    if isinstance(lists, np.ndarray):  # one length for all
        faces = lists.astype(np.int64)
        origin = np.arange(len(faces))
    else:
        sizes = {len(f) for f in lists}
        if len(sizes) == 1:
            faces, origin = np.array(lists, dtype=np.int64), np.arange(len(lists))
        else:
            tris, origin = [], []
            for i, f in enumerate(lists):
                f = [int(v) for v in f]
                for c in range(1, len(f) - 1):
                    tris.append([f[0], f[c], f[c + 1]])
                    origin.append(i)
            faces, origin = np.array(tris, dtype=np.int64).reshape(-1, 3), np.array(origin)
    if faces.ndim != 2 or (len(faces) and faces.shape[1] < 3):
        raise InputError(f"{path}: faces with fewer than 3 corners; expected polygons")
    bad = (faces < 0) | (faces >= vertex_count)
    if bad.any():
        row, corner = np.argwhere(bad)[0]
        raise InputError(f"{path}: face {origin[row] + 1}{located(origin[row])} references vertex "
                         f"{faces[row, corner]}, but the file has {vertex_count} (indices run 0..{vertex_count - 1})")
    return faces


def read_ply(path: str | os.PathLike) -> PlyMesh:
    """Read a PLY mesh or point cloud (ascii or binary, either byte order): see the module docstring."""
    path = require_file(path)
    data = path.read_bytes()
    fmt, elements, body, header_lines = _parse_header(data, path)
    names = [e.name for e in elements]
    if "vertex" not in names:
        raise InputError(f"{path}: no 'element vertex' in the header; expected a mesh or point cloud")
    vertex = elements[names.index("vertex")]
    props = [p.name for p in vertex.properties]
    missing = [axis for axis in "xyz" if axis not in props]
    if missing:
        raise InputError(f"{path}: the vertex element lacks {', '.join(missing)} (header line {vertex.line}); "
                         "expected properties x, y, z")
    if fmt == "ascii":
        values, locate = _read_ascii(data, path, elements, body, header_lines + 1)
    else:
        values, locate = _read_binary(data, path, elements, body, FORMATS[fmt])
    columns = values["vertex"]
    vertices = np.stack([np.asarray(columns[a], dtype=np.float64) for a in "xyz"], axis=1).reshape(-1, 3)
    if len(vertices) == 0:
        raise InputError(f"{path}: 0 vertices; expected a mesh or point cloud")
    bad = ~np.isfinite(vertices).all(axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputError(f"{path}: vertex {i + 1}{locate['vertex'](i)} is not finite ({vertices[i].tolist()})")
    normals = None
    if all(a in props for a in ("nx", "ny", "nz")):
        normals = np.stack([np.asarray(columns[a], dtype=np.float64) for a in ("nx", "ny", "nz")], axis=1)
    faces = np.zeros((0, 3), dtype=np.int64)
    if "face" in names:
        face = elements[names.index("face")]
        key = next((p.name for p in face.properties if p.name in FACE_LISTS and p.count_type), None)
        if key is None and face.count:
            raise InputError(f"{path}: the face element (header line {face.line}) has no list property "
                             f"{' or '.join(FACE_LISTS)}")
        if face.count:
            faces = _faces(values["face"][key], path, len(vertices), locate["face"])
    return PlyMesh(vertices, faces, normals)
