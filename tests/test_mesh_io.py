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
