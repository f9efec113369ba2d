"""OBJ reading: index conventions and errors that point at the bad face."""
from __future__ import annotations

import numpy as np
import pytest

from base.errors import InputError
from data.mesh_io import read_obj

SQUARE = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvt 0 0\nvt 1 0\nvt 1 1\nvt 0 1\n"


def test_positive_and_negative_indices_agree(tmp_path):
    """Index 1 is the first vertex, -1 the last one read: the same quad written both ways."""
    (tmp_path / "pos.obj").write_text(SQUARE + "f 1/1 2/2 3/3 4/4\n")
    (tmp_path / "neg.obj").write_text(SQUARE + "f -4/-4 -3/-3 -2/-2 -1/-1\n")
    pos, neg = read_obj(tmp_path / "pos.obj"), read_obj(tmp_path / "neg.obj")
    assert pos.faces.tolist() == [[0, 1, 2, 3]] and neg.faces.tolist() == [[0, 1, 2, 3]]
    assert np.array_equal(pos.faces_uv, neg.faces_uv)


@pytest.mark.parametrize("faces, message", [
    ("f 1 2 3\nf 2 3 9\n", r"bad\.obj: 'f' record 2 references vertex 9, but the file has 4"),
    ("f 0 1 2\n", r"bad\.obj: 'f' record 1 references vertex 0, but the file has 4"),
    ("f 1 2 3\nf -5 1 2\n", r"bad\.obj: 'f' record 2 references vertex -5, but the file has 4"),
    ("f 1/1 2/2 3/7\n", r"bad\.obj: 'f' record 1 references texture coordinate 7, but the file has 4"),
    ("f 1 2 3 4\nf 1 2 8\n", r"bad\.obj: triangle \(polygons fan-triangulated\) 3 references vertex 8"),
])
def test_out_of_range_index_names_the_face_and_the_index_as_written(tmp_path, faces, message):
    (tmp_path / "bad.obj").write_text(SQUARE + faces)
    with pytest.raises(InputError, match=message):
        read_obj(tmp_path / "bad.obj")


# PLY: a small mesh written by the test's own writer in each of the three encodings.
PLY_TYPES = {"f4": "float", "f8": "double", "i4": "int", "u1": "uchar", "i2": "short"}


def write_test_ply(path, vertices, faces=None, normals=None, fmt="ascii", extra_element=False):
    """A PLY with float vertices (+ normals), a face list (uchar counts, int indices; faces a list of
    lists, any sizes), and optionally a leading 'edge' element the reader must skip."""
    order = {"ascii": "", "binary_little_endian": "<", "binary_big_endian": ">"}[fmt]
    props = ["x", "y", "z"] + (["nx", "ny", "nz"] if normals is not None else [])
    table = vertices if normals is None else np.concatenate([vertices, normals], axis=1)
    lines = ["ply", f"format {fmt} 1.0", "comment made by the test"]
    if extra_element:
        lines += ["element edge 2", "property int vertex1", "property int vertex2"]
    lines += [f"element vertex {len(vertices)}"] + [f"property float {p}" for p in props]
    if faces is not None:
        lines += [f"element face {len(faces)}", "property list uchar int vertex_indices"]
    header = ("\n".join(lines + ["end_header"]) + "\n").encode()
    if fmt == "ascii":
        body = ("0 1\n1 2\n" if extra_element else "")
        body += "".join(" ".join(f"{v:.7g}" for v in row) + "\n" for row in table)
        body += "".join(f"{len(f)} " + " ".join(str(i) for i in f) + "\n" for f in (faces or []))
        path.write_bytes(header + body.encode())
        return
    parts = [np.array([[0, 1], [1, 2]], dtype=order + "i4").tobytes()] if extra_element else []
    parts.append(np.asarray(table, dtype=order + "f4").tobytes())
    for f in faces or []:
        parts.append(np.array([len(f)], "u1").tobytes() + np.array(f, dtype=order + "i4").tobytes())
    path.write_bytes(header + b"".join(parts))


CUBE = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], float) * 1.5
NORMALS = CUBE - 0.75
QUADS = [[0, 1, 2, 3], [4, 5, 6, 7], [0, 1, 5, 4]]


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_ply_reads_vertices_normals_faces_in_every_encoding(tmp_path, fmt):
    from data.mesh_io import read_ply

    path = tmp_path / "cube.ply"
    write_test_ply(path, CUBE, QUADS, NORMALS, fmt, extra_element=True)
    mesh = read_ply(path)
    assert np.allclose(mesh.vertices, CUBE, atol=1e-6)
    assert np.allclose(mesh.normals, NORMALS, atol=1e-6)
    assert mesh.faces.tolist() == QUADS


@pytest.mark.parametrize("fmt", ["ascii", "binary_big_endian"])
def test_ply_point_cloud_and_mixed_polygons(tmp_path, fmt):
    """No face element: a point cloud ([0,3] faces, no normals); a triangle beside a quad: fanned."""
    from data.mesh_io import read_ply

    write_test_ply(tmp_path / "cloud.ply", CUBE, fmt=fmt)
    cloud = read_ply(tmp_path / "cloud.ply")
    assert cloud.vertices.shape == (8, 3) and cloud.faces.shape == (0, 3) and cloud.normals is None
    write_test_ply(tmp_path / "mixed.ply", CUBE, [[0, 1, 2], [4, 5, 6, 7]], fmt=fmt)
    assert read_ply(tmp_path / "mixed.ply").faces.tolist() == [[0, 1, 2], [4, 5, 6], [4, 6, 7]]


def test_ply_reads_what_write_ply_writes(tmp_path):
    from data.mesh_io import read_ply, write_ply

    write_ply(tmp_path / "w.ply", CUBE, np.array(QUADS))
    mesh = read_ply(tmp_path / "w.ply")
    assert np.allclose(mesh.vertices, CUBE) and mesh.faces.tolist() == QUADS


def test_ply_errors_name_the_file_and_the_line_or_byte(tmp_path):
    from data.mesh_io import read_ply

    def fails(name, data, message):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(InputError, match=message):
            read_ply(tmp_path / name)

    write_test_ply(tmp_path / "good.ply", CUBE, QUADS, fmt="binary_little_endian")
    good = (tmp_path / "good.ply").read_bytes()
    header = good.index(b"end_header\n") + len(b"end_header\n")
    # cut inside vertex 5 (12 bytes a vertex): the byte where the file ends and the record are named
    fails("cut.ply", good[:header + 4 * 12 + 6], rf"cut\.ply: the file ends at byte {header + 54} inside 'vertex' "
          r"record 5 of 8 \(the element starts at byte " + str(header))
    fails("cutface.ply", good[:-3], r"cutface\.ply: .*'face' record 3 .*truncated")
    ascii_lines = ["ply", "format ascii 1.0", "element vertex 3", "property float x", "property float y",
                   "property float z", "element face 1", "property list uchar int vertex_indices", "end_header"]
    head = "\n".join(ascii_lines) + "\n"
    fails("short.ply", (head + "0 0 0\n1 0\n0 1 0\n3 0 1 2\n").encode(),
          r"short\.ply: line 11: 2 numbers, expected 3 \('vertex' record 2\)")
    fails("word.ply", (head + "0 0 0\n1 0 0\n0 one 0\n3 0 1 2\n").encode(), r"word\.ply: line 12: not a number")
    fails("nan.ply", (head + "0 0 0\n1 0 0\n0 nan 0\n3 0 1 2\n").encode(),
          r"nan\.ply: vertex 3 \(line 12\) is not finite")
    fails("index.ply", (head + "0 0 0\n1 0 0\n0 1 0\n3 0 1 3\n").encode(),
          r"index\.ply: face 1 \(line 13\) references vertex 3, but the file has 3")
    fails("few.ply", (head + "0 0 0\n1 0 0\n").encode(), r"few\.ply: the file ends after 2 of the 3 'vertex' records")
    fails("obj.ply", b"v 0 0 0\n", r"obj\.ply: does not start with 'ply'")
    fails("fmt.ply", b"ply\nformat binary_middle_endian 1.0\nend_header\n", r"fmt\.ply: header line 2: format")
    fails("noxyz.ply", b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n0\n",
          r"noxyz\.ply: the vertex element lacks y, z")
    fails("empty.ply", b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
          b"property float z\nend_header\n", r"empty\.ply: 0 vertices")


def test_read_points_takes_obj_and_ply_and_refuses_other_files(tmp_path):
    from data.mesh_io import read_points

    (tmp_path / "a.obj").write_text("v 0 0 0\nv 1 2 3\n")
    assert read_points(tmp_path / "a.obj").tolist() == [[0, 0, 0], [1, 2, 3]]
    (tmp_path / "n.obj").write_text("v 0 0 0\nv 1 nan 3\n")
    with pytest.raises(InputError, match=r"n\.obj: vertex 2 \('v' record\) is not finite"):
        read_points(tmp_path / "n.obj")
    (tmp_path / "a.stl").write_text("solid")
    with pytest.raises(InputError, match=r"a\.stl: a \.stl file; expected a mesh or point cloud"):
        read_points(tmp_path / "a.stl")


def test_ply_ascii_records_must_each_hold_their_numbers(tmp_path):
    """The right total count of numbers spread wrongly over the lines is still an error naming the line."""
    from data.mesh_io import read_ply

    head = "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\nproperty float z\nend_header\n"
    (tmp_path / "shifted.ply").write_text(head + "0 0\n1 0 0 0\n")
    with pytest.raises(InputError, match=r"shifted\.ply: line 8: 2 numbers, expected 3"):
        read_ply(tmp_path / "shifted.ply")


def test_ply_scanner_layout_with_colours_and_extra_face_properties(tmp_path):
    """A scanner's binary PLY: double positions, uchar colours and a float confidence between them, faces with
    a ushort count type, uint indices and a per-face int after the list."""
    from data.mesh_io import read_ply

    header = (b"ply\nformat binary_big_endian 1.0\nobj_info scanner\nelement vertex 8\nproperty double x\n"
              b"property uchar red\nproperty uchar green\nproperty uchar blue\nproperty double y\nproperty float "
              b"confidence\nproperty double z\nelement face 3\nproperty list ushort uint vertex_index\n"
              b"property int flags\nend_header\n")
    vertex = np.zeros(8, dtype=[("x", ">f8"), ("rgb", "u1", 3), ("y", ">f8"), ("c", ">f4"), ("z", ">f8")])
    vertex["x"], vertex["y"], vertex["z"], vertex["rgb"] = CUBE[:, 0], CUBE[:, 1], CUBE[:, 2], 200
    face = np.zeros(3, dtype=[("n", ">u2"), ("idx", ">u4", 4), ("flags", ">i4")])
    face["n"], face["idx"], face["flags"] = 4, QUADS, -1
    (tmp_path / "scan.ply").write_bytes(header + vertex.tobytes() + face.tobytes())
    mesh = read_ply(tmp_path / "scan.ply")
    assert np.array_equal(mesh.vertices, CUBE) and mesh.faces.tolist() == QUADS and mesh.normals is None
