"""Shared file I/O: tau tracks, CSV errors, atomic writes."""
from __future__ import annotations

import numpy as np
import pytest

from base.cli import as_list
from base.errors import InputError
from base.files import atomic_path, save_npy, write_csv
from base.tables import CsvTable
from data.tau_track import read_tau_track


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


def test_min_confidence_ignored_without_a_confidence_column(tmp_path):
    write_csv(tmp_path / "plain.csv", {"time": np.arange(4) / 10.0, "tau": [0.0, 0.01, 0.02, 0.03]})
    track = read_tau_track(tmp_path / "plain.csv", min_confidence=0.3)
    np.testing.assert_allclose(track.tau, [0.0, 0.01, 0.02, 0.03])
    assert track.fps == 10.0


def test_tracker_csv_without_calibration_says_so(tmp_path):
    """motion.track without px_per_tau writes tau_px and a NaN tau column."""
    write_csv(tmp_path / "uncal.csv", {"frame": np.arange(5), "time": np.arange(5) / 30.0,
                                       "tau_px": [0.0, 1.0, 2.0, 1.5, 0.5], "tau": np.full(5, np.nan),
                                       "confidence": np.full(5, 0.9)})
    for min_confidence in (None, 0.3):
        with pytest.raises(InputError, match=r"uncal\.csv: .*no calibration.*px_per_tau=.*cm_per_px=.*kernel=rig"):
            read_tau_track(tmp_path / "uncal.csv", min_confidence=min_confidence)


def test_rate_from_the_caller_only_where_the_file_has_none(tmp_path):
    (tmp_path / "frames.csv").write_text("frame,tau\n0,0\n1,0.1\n2,0.2\n")
    with pytest.raises(InputError,
                       match=r"frames\.csv: column 'frame' without a 'time' or 'fps' column; give track_fps="):
        read_tau_track(tmp_path / "frames.csv", fps_key="track_fps")
    np.testing.assert_allclose(read_tau_track(tmp_path / "frames.csv", fps=20).time, [0.0, 0.05, 0.1])
    save_npy(tmp_path / "t.npy", np.zeros(4))
    with pytest.raises(InputError, match=r"t\.npy: a \.npy tau track carries no frame rate; give my_rate="):
        read_tau_track(tmp_path / "t.npy", fps_key="my_rate")
    # A file's own rate wins over the caller's fallback: its fps column, or its time stamps.
    (tmp_path / "own.csv").write_text("frame,tau,fps\n0,0,25\n1,0.1,25\n")
    own = read_tau_track(tmp_path / "own.csv", fps=60)
    assert own.fps == 25.0 and own.time[1] == pytest.approx(0.04)
    (tmp_path / "timed.csv").write_text("time,tau\n0,0\n0.1,0.1\n0.2,0\n")
    assert read_tau_track(tmp_path / "timed.csv", fps=60).fps == 10.0
    (tmp_path / "one.csv").write_text("time,tau\n0,0\n")
    with pytest.raises(InputError, match=r"one\.csv: one row only; give fps="):
        read_tau_track(tmp_path / "one.csv")
    assert read_tau_track(tmp_path / "one.csv", fps=30).fps == 30.0


def test_headerless_table_names_line_and_column(tmp_path):
    (tmp_path / "plain.csv").write_bytes("\ufeff1,2\n3,inf\n".encode("utf-8"))  # with a UTF-8 byte-order mark
    with pytest.raises(InputError, match=r"plain\.csv: column 'b', line 2: value is inf, expected finite"):
        CsvTable(tmp_path / "plain.csv", columns=["a", "b"]).numeric("b")
    table = CsvTable(tmp_path / "plain.csv", columns=["a", "b"])
    np.testing.assert_array_equal(table.numeric("a"), [1.0, 3.0])  # the first row is data, the mark is gone
    (tmp_path / "ragged.csv").write_text("1,2\n3\n")
    with pytest.raises(InputError, match=r"ragged\.csv: line 2 has 1 cells, expected 2"):
        CsvTable(tmp_path / "ragged.csv", columns=["a", "b"])


def test_as_list_takes_one_value_or_a_list():
    from omegaconf import OmegaConf

    assert as_list("a.csv") == ["a.csv"]  # a string is one item, not its characters
    assert as_list(2.0) == [2.0] and as_list(0) == [0]
    assert as_list(None) == [] and as_list([]) == []
    assert as_list((1, 2)) == [1, 2]
    listed = as_list(OmegaConf.create({"at": [1.5, 2.5]}).at)
    assert listed == [1.5, 2.5] and isinstance(listed, list)


def test_atomic_path_leaves_the_old_file_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("half")
            raise RuntimeError("crash while writing")
    assert target.read_text() == "old" and list(tmp_path.iterdir()) == [target]


STAGE_AND_HANG = """
import sys, time
from pathlib import Path
from base.files import atomic_folder
with atomic_folder(Path(sys.argv[1])) as staging:
    (staging / "params.npz").write_bytes(b"half")
    print("staged", flush=True)
    time.sleep(60)
"""


def test_atomic_folder_sweeps_the_staging_of_a_killed_run(tmp_path):
    """An infer.py run SIGKILLed while writing leaves its ``.partial`` staging folder (no ``finally`` runs);
    the next run for the same out_dir removes it, and names it.  A live process's, another machine's and
    another out_dir's are left."""
    import os
    import signal
    import socket
    import subprocess
    import sys

    from base.files import atomic_folder, stale_staging
    from tests.conftest import REPO

    out = tmp_path / "take"
    child = subprocess.Popen([sys.executable, "-c", STAGE_AND_HANG, str(out)], stdout=subprocess.PIPE, text=True,
                             cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)})
    try:
        assert child.stdout.readline().strip() == "staged"
        (killed,) = [p for p in tmp_path.iterdir() if p.name.endswith(".partial")]
        assert stale_staging(out) == []                                  # its process is alive: not stale
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait()
        child.stdout.close()
    assert (killed / "params.npz").read_bytes() == b"half" and not out.exists()
    assert stale_staging(out) == [killed]
    host = socket.gethostname()
    kept = [tmp_path / f".take.{host}-{os.getpid()}.abcd1234.partial",       # this process: alive
            tmp_path / ".take.another-host-1.abcd1234.partial",              # another machine's
            tmp_path / f".take2.{host}-{child.pid}.abcd1234.partial"]        # another out_dir's
    for path in kept:
        path.mkdir()
    said = []
    with atomic_folder(out, said.append) as staging:
        (staging / "params.npz").write_bytes(b"whole")
    assert (out / "params.npz").read_bytes() == b"whole"
    assert not killed.exists() and all(path.is_dir() for path in kept)
    assert said == [f"{out}: removed {killed.name}, the unfinished output of a run that was killed"]
