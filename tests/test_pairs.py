"""Pair files and the capture alignment CLI (data/pairs/__init__.py)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from base.errors import InputError
from base.files import save_npy, save_npz, write_csv
from data.expressions import EXPRESSION_NAMES, read_expressions
from data.pairs import LarynxSequence, align_pair, load_pair, load_pairs, save_pair, split_by_take, take_from_name
from data.splits import split_by_file
from data.tau_track import read_tau_track

REPO = Path(__file__).resolve().parents[1]
JAW = EXPRESSION_NAMES.index("jawOpen")
TRACK_START = 0.5  # the larynx tracker started 0.5 s after the face capture


def true_tau(t):
    """The larynx slide on the face-capture clock (UV units)."""
    return 0.02 * np.sin(2 * np.pi * 0.7 * t) + 0.01 * t


def true_jaw(t):
    return 0.5 + 0.4 * np.sin(2 * np.pi * 0.3 * t)


@pytest.fixture
def capture(tmp_path):
    """An expression take at 60 fps (0-8 s) and a tracker CSV at 25 fps that started 0.5 s later (6 s long)."""
    face_time = np.arange(481) / 60
    columns = {"time": face_time, "jawOpen": true_jaw(face_time), "mouthPress_L": np.full(481, 0.1)}
    write_csv(tmp_path / "take.csv", columns, float_format="%.9g")
    track_time = np.arange(151) / 25  # the tracker's own clock
    tau = true_tau(track_time + TRACK_START)
    write_csv(tmp_path / "track.csv", {
        "frame": np.arange(151), "time": track_time, "x_px": np.full(151, 320.0), "y_px": 400 - 3000 * tau,
        "tau_px": -3000 * tau, "tau": tau, "confidence": np.full(151, 0.9)}, float_format="%.9g")
    return tmp_path / "track.csv", tmp_path / "take.csv"


def test_alignment_by_time_with_known_offset(capture):
    track, take = read_tau_track(capture[0]), read_expressions(capture[1])
    pair, time = align_pair(track, take, fps=30, offset=TRACK_START, subject="anna")
    assert len(pair) == 181 and pair.fps == 30  # overlap 0.5-6.5 s at 30 fps
    np.testing.assert_allclose(time, TRACK_START + np.arange(181) / 30, atol=1e-9)
    # Linear interpolation of the 25 fps track: error <= h^2/8 * max|tau''| ~ 8e-5.
    np.testing.assert_allclose(pair.tau, true_tau(time), atol=2e-4)
    np.testing.assert_allclose(pair.psi[:, JAW], true_jaw(time), atol=2e-4)
    assert pair.subject == "anna"
    # Without the offset the track is 0.5 s early: errors of the order of the signal.
    wrong, wrong_time = align_pair(track, take, fps=30, offset=0.0)
    assert np.abs(wrong.tau - true_tau(wrong_time)).max() > 0.01


def test_cli_round_trip(capture, tmp_path):
    out = tmp_path / "pairs" / "take1.npz"
    result = subprocess.run(
        [sys.executable, "-m", "data.pairs", f"track={capture[0]}", f"expressions={capture[1]}", f"out={out}",
         f"offset={TRACK_START}", "subject=anna"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode == 0, result.stderr
    pair = load_pair(out)
    assert pair.fps == pytest.approx(60.0) and len(pair) == 361  # default rate: the expression recording's
    time = TRACK_START + np.arange(361) / 60
    np.testing.assert_allclose(np.load(out)["time"], time, atol=1e-9)
    np.testing.assert_allclose(pair.tau, true_tau(time), atol=2e-4)
    np.testing.assert_allclose(pair.psi[:, JAW], true_jaw(time), atol=1e-5)
    assert pair.subject == "anna" and pair.name == "take1"
    assert not list(out.parent.glob(".*tmp*"))  # atomic write left no temporary file


def test_cli_reports_no_overlap(capture, tmp_path):
    out = tmp_path / "pair.npz"
    result = subprocess.run(
        [sys.executable, "-m", "data.pairs", f"track={capture[0]}", f"expressions={capture[1]}", f"out={out}",
         "offset=20"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert result.returncode != 0
    assert "error:" in result.stderr and "track.csv covers 20.000-26.000 s" in result.stderr
    assert "take.csv covers 0.000-8.000 s" in result.stderr and "offset" in result.stderr
    assert not out.exists()


def compose_pairs(overrides):
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("pairs", overrides=[str(o) for o in overrides])


def test_cli_asks_for_the_rates_by_their_keys(capture, tmp_path):
    """In python -m data.pairs, fps is the output rate: a missing input rate is asked for by its own key."""
    from data.pairs import run

    track, take = capture
    out = tmp_path / "pair.npz"
    save_npy(tmp_path / "track.npy", true_tau(np.arange(100) / 25))
    with pytest.raises(InputError, match=r"track\.npy: a \.npy tau track carries no frame rate; give track_fps="):
        run(compose_pairs([f"track={tmp_path / 'track.npy'}", f"expressions={take}", f"out={out}", "fps=30"]))
    np.savetxt(tmp_path / "plain.csv", np.full((50, 55), 0.2), delimiter=",")
    with pytest.raises(InputError,
                       match=r"plain\.csv: a header-less table carries no frame rate; give expressions_fps="):
        run(compose_pairs([f"track={track}", f"expressions={tmp_path / 'plain.csv'}", f"out={out}", "fps=30"]))
    assert not out.exists()
    pair = run(compose_pairs([f"track={tmp_path / 'track.npy'}", "track_fps=25",
                              f"expressions={tmp_path / 'plain.csv'}", "expressions_fps=10", f"out={out}", "fps=20"]))
    assert pair.fps == 20 and len(pair) == 80  # overlap: the track's 100 frames at 25 fps, 0-3.96 s
    np.testing.assert_allclose(pair.tau, true_tau(np.arange(len(pair)) / 20), atol=2e-4)


def test_cli_passes_timecode_fps(capture, tmp_path):
    """A Live Link Face take under one second: the timecode rate comes from timecode_fps."""
    from data.pairs import run

    header = ["Timecode", "BlendShapeCount", "JawOpen", "HeadYaw", "HeadPitch", "HeadRoll"]
    rows = [f"10:00:00:{f:02d}.000,61,{true_jaw(f / 25):.6f},0,0,0" for f in range(20)]
    (tmp_path / "short.csv").write_text(",".join(header) + "\n" + "\n".join(rows) + "\n")
    args = [f"track={capture[0]}", f"expressions={tmp_path / 'short.csv'}", f"out={tmp_path / 'pair.npz'}"]
    with pytest.raises(InputError, match=r"short\.csv: column 'Timecode': .*give timecode_fps="):
        run(compose_pairs(args))
    pair = run(compose_pairs(args + ["timecode_fps=25"]))
    assert pair.fps == pytest.approx(25.0) and len(pair) == 20  # the take's rate and frames (0-0.76 s)
    np.testing.assert_allclose(pair.psi[:, JAW], true_jaw(np.arange(20) / 25), atol=1e-5)


def make_sequence(length=40, fps=30.0, subject="anna", seed=0):
    rng = np.random.default_rng(seed)
    return LarynxSequence(rng.uniform(0, 1, (length, 55)).astype(np.float32),
                          (0.01 * rng.standard_normal(length)).astype(np.float32), fps, subject, f"seq{seed}")


def test_save_load_round_trip(tmp_path):
    sequence = make_sequence()
    sequence.eta = 1.1
    save_pair(tmp_path / "a.npz", sequence)
    loaded = load_pair(tmp_path / "a.npz")
    np.testing.assert_array_equal(loaded.psi, sequence.psi)
    np.testing.assert_array_equal(loaded.tau, sequence.tau)
    assert (loaded.fps, loaded.subject, loaded.eta, loaded.name) == (30.0, "anna", 1.1, "a")
    assert loaded.take == sequence.name  # a sequence is its own take unless told otherwise, and the file says so
    sequence.take = "anna_monday"
    save_pair(tmp_path / "b.npz", sequence)
    assert load_pair(tmp_path / "b.npz").take == "anna_monday"


@pytest.mark.parametrize("stem, take", [("anna_take2_clip07", "anna_take2"), ("anna_take2-08", "anna_take2"),
                                        ("take3", "take3"), ("ben_03", "ben"), ("ben part 3", "ben"),
                                        ("007", "007"), ("s1_seg12", "s1")])
def test_take_from_a_file_name(stem, take):
    assert take_from_name(stem) == take


def test_files_without_take_are_grouped_by_name(tmp_path):
    for name in ("anna_take1_clip01", "anna_take1_clip02", "ben_take1_clip01"):
        arrays = {"psi": np.full((10, 55), 0.2, np.float32), "tau": np.zeros(10, np.float32), "fps": np.float64(30)}
        save_npz(tmp_path / f"{name}.npz", **arrays)  # written by another tool: no take entry
    assert [p.take for p in load_pairs(tmp_path)] == ["anna_take1", "anna_take1", "ben_take1"]


def test_split_by_take_keeps_clips_of_a_take_together(capsys):
    takes = [f"take{k}" for k in range(5)]
    pairs = [LarynxSequence(np.zeros((5, 55), np.float32), np.zeros(5, np.float32), 30.0, None, f"{t}_clip{c}", take=t)
             for t in takes for c in range(4)]
    for seed in range(6):
        train, val = split_by_take(pairs, 0.2, seed)
        assert len({p.take for p in val}) == 1 and len(val) == 4  # one take of five, with all its clips
        assert not {p.take for p in train} & {p.take for p in val}
        assert len(train) + len(val) == len(pairs)
    assert len({split_by_take(pairs, 0.2, seed)[1][0].take for seed in range(10)}) > 1  # the seed chooses
    one_take = [LarynxSequence(p.psi, p.tau, 30.0, None, p.name, take="only") for p in pairs[:5]]
    train, val = split_by_take(one_take, 0.2, 0)
    assert (len(train), len(val)) == (4, 1)  # a single take: split by file, and said
    assert "all 5 pair files are one take ('only'): validation by file" in capsys.readouterr().out


@pytest.mark.parametrize("change, match", [
    (lambda a: a.pop("tau"), r"bad.npz: no 'tau' array \(found: fps, psi\)"),
    (lambda a: a.update(psi=a["psi"][:, :54]), r"bad.npz: 'psi' has shape \(10, 54\)"),
    (lambda a: a.update(tau=a["tau"][:9]), r"bad.npz: 'psi' has 10 frames but 'tau' has 9"),
    (lambda a: a["tau"].__setitem__(3, np.nan), r"bad.npz: 'tau' is not finite at frame 3"),
    (lambda a: a["psi"].__setitem__((4, JAW), 3.0), r"bad.npz: column 'jawOpen', row 4: weight 3 outside"),
    (lambda a: a.update(fps=np.float64(-30)), r"bad.npz: 'fps' is -30, expected a positive frame rate"),
    (lambda a: a.update(subject=np.int64(3)), r"bad.npz: 'subject' is .*, expected a name"),
])
def test_load_errors_name_file_and_key(tmp_path, change, match):
    arrays = {"psi": np.full((10, 55), 0.2, np.float32), "tau": np.zeros(10, np.float32), "fps": np.float64(30)}
    change(arrays)
    save_npz(tmp_path / "bad.npz", **arrays)
    with pytest.raises(InputError, match=match):
        load_pair(tmp_path / "bad.npz")


def test_load_rejects_non_archives(tmp_path):
    (tmp_path / "junk.npz").write_text("not an archive")
    with pytest.raises(InputError, match="junk.npz: not a readable .npz archive"):
        load_pair(tmp_path / "junk.npz")
    with pytest.raises(InputError, match="nowhere: not a folder"):
        load_pairs(tmp_path / "nowhere")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="empty: no .npz pair files"):
        load_pairs(tmp_path / "empty")


def test_load_pairs_resamples_to_one_rate(tmp_path):
    time = np.arange(61) / 60
    sequence = LarynxSequence(np.tile(true_jaw(time)[:, None], (1, 55)).astype(np.float32),
                              true_tau(time).astype(np.float32), 60.0, None, "fast")
    save_pair(tmp_path / "fast.npz", sequence)
    save_pair(tmp_path / "slow.npz", make_sequence(length=31, fps=30.0))
    fast, slow = load_pairs(tmp_path, fps=30)
    assert (fast.name, len(fast), fast.fps, len(slow)) == ("fast", 31, 30.0, 31)
    np.testing.assert_allclose(fast.tau, true_tau(np.arange(31) / 30), atol=1e-6)
    assert fast.subject is None


def test_split_by_file(tmp_path):
    pairs = [make_sequence(seed=i) for i in range(10)]
    train, val = split_by_file(pairs, 0.2, seed=3, what="pair file")
    assert (len(train), len(val)) == (8, 2)
    assert {p.name for p in train} | {p.name for p in val} == {p.name for p in pairs}
    assert not {p.name for p in train} & {p.name for p in val}
    again_train, again_val = split_by_file(pairs, 0.2, seed=3)
    assert [p.name for p in again_val] == [p.name for p in val]
    other_seeds = {tuple(p.name for p in split_by_file(pairs, 0.2, seed=s)[1]) for s in range(10)}
    assert len(other_seeds) > 1                                 # the seed chooses the held-out files
    assert len(split_by_file(pairs[:2], 0.01, 0)[1]) == 1 and len(split_by_file(pairs[:2], 0.99, 0)[0]) == 1
    with pytest.raises(InputError, match="1 pair file"):
        split_by_file(pairs[:1], 0.2, 0, "pair file")
    with pytest.raises(InputError, match=r"val_fraction must be in \(0, 1\), got 1.5"):
        split_by_file(pairs, 1.5, 0)
