"""Shared file I/O: tau tracks, CSV errors, atomic writes."""
from __future__ import annotations

import numpy as np
import pytest

from data.io import InputError, atomic_path, read_tau_track, write_csv


def test_tracker_rows_below_confidence_are_dropped(tmp_path):
    time = np.arange(6) / 30.0
    write_csv(tmp_path / "track.csv", {"frame": np.arange(6), "time": time, "tau": [0, 0.01, np.nan, 0.03, 0.04, 0.05],
                                       "confidence": [0.9, 0.8, 0.0, 0.9, 0.95, 0.9]}, float_format="%.9g")
    kept = read_tau_track(tmp_path / "track.csv", min_confidence=0.3)
    np.testing.assert_allclose(kept.tau, [0, 0.01, 0.03, 0.04, 0.05])
    np.testing.assert_allclose(kept.time, time[[0, 1, 3, 4, 5]])
    assert kept.fps == 30.0  # from the time stamps, rounded to 1e-3
    with pytest.raises(InputError, match="column 'tau', line 4: value is nan"):  # a lost frame, unfiltered
        read_tau_track(tmp_path / "track.csv")


@pytest.mark.parametrize("rows, message", [
    ("time,tau\n0,0\n0.1,x\n", r"column 'tau', line 3: expected a number, found 'x'"),
    ("time,tau\n0,0\n0,0.1\n", r"column 'time' must increase, but line 3"),
    ("frame,tau\n0,0\n1,0.1\n", r"column 'frame' without a 'time' or 'fps' column; give fps="),
    ("time,value\n0,0\n", r"no column 'tau'"),
])
def test_bad_tau_tracks_name_the_file_and_line(tmp_path, rows, message):
    (tmp_path / "bad.csv").write_text(rows)
    with pytest.raises(InputError, match=f"bad.csv: {message}"):
        read_tau_track(tmp_path / "bad.csv")


def test_atomic_path_leaves_the_old_file_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash while writing")
    assert target.read_text() == "old" and list(tmp_path.iterdir()) == [target]
