"""The shared expression reader (data/expressions.py): formats, name mapping, timecodes, errors."""
from __future__ import annotations

import numpy as np
import pytest

from base.errors import InputError
from data.expressions import EXPRESSION_NAMES, read_expressions

K = {name: k for k, name in enumerate(EXPRESSION_NAMES)}

# Live Link Face's column order (Epic Games' Live Link Face app, CSV export), written out here on purpose.
ARKIT = (
    "EyeBlinkLeft EyeLookDownLeft EyeLookInLeft EyeLookOutLeft EyeLookUpLeft EyeSquintLeft EyeWideLeft "
    "EyeBlinkRight EyeLookDownRight EyeLookInRight EyeLookOutRight EyeLookUpRight EyeSquintRight EyeWideRight "
    "JawForward JawRight JawLeft JawOpen MouthClose MouthFunnel MouthPucker MouthRight MouthLeft MouthSmileLeft "
    "MouthSmileRight MouthFrownLeft MouthFrownRight MouthDimpleLeft MouthDimpleRight MouthStretchLeft "
    "MouthStretchRight MouthRollLower MouthRollUpper MouthShrugLower MouthShrugUpper MouthPressLeft "
    "MouthPressRight MouthLowerDownLeft MouthLowerDownRight MouthUpperUpLeft MouthUpperUpRight BrowDownLeft "
    "BrowDownRight BrowInnerUp BrowOuterUpLeft BrowOuterUpRight CheekPuff CheekSquintLeft CheekSquintRight "
    "NoseSneerLeft NoseSneerRight TongueOut"
).split()
LLF_HEADER = ["Timecode", "BlendShapeCount", *ARKIT, "HeadYaw", "HeadPitch", "HeadRoll", "LeftEyeYaw",
              "LeftEyePitch", "LeftEyeRoll", "RightEyeYaw", "RightEyePitch", "RightEyeRoll"]


def llf_rows(count: int, head: float = 0.0, start_frame: int = 50):
    """Rows of a Live Link Face take at 30 Hz with a 60 fps timecode (frame numbers step by 2)."""
    rows, codes = [], []
    for i in range(count):
        frame = start_frame + 2 * i  # 60 fps timecode frames, wrapping into the next second
        seconds, ff = divmod(frame, 60)
        code = f"12:21:{59 + seconds:02d}:{ff:02d}.250" if seconds == 0 else f"12:22:{seconds - 1:02d}:{ff:02d}.250"
        values = {name: 0.0 for name in ARKIT}
        values.update(EyeBlinkLeft=0.05 * i, JawOpen=0.3, BrowInnerUp=0.5, CheekPuff=0.25, TongueOut=0.9,
                      MouthSmileRight=0.125)
        cells = [code, "61", *[f"{values[n]:.6f}" for n in ARKIT], f"{head:.3f}", f"{-head:.3f}", "0.0",
                 *["0.0"] * 6]
        rows.append(",".join(cells))
        codes.append(code)
    return rows, codes


def write(path, header, rows):
    path.write_text(",".join(header) + "\n" + "\n".join(rows) + "\n")
    return path


def test_live_link_face_timecode_and_names(tmp_path):
    rows, codes = llf_rows(12)
    assert codes[4].startswith("12:21:59:") and codes[5].startswith("12:22:00:")  # the take crosses a second boundary
    track = read_expressions(write(tmp_path / "take.csv", LLF_HEADER, rows))
    assert track.psi.shape == (12, 55)
    np.testing.assert_allclose(track.time, np.arange(12) * 2 / 60, atol=1e-9)
    assert track.fps == pytest.approx(30.0, rel=1e-6)
    np.testing.assert_allclose(track.psi[:, K["eyeBlink_L"]], 0.05 * np.arange(12), atol=1e-6)
    np.testing.assert_allclose(track.psi[:, K["jawOpen"]], 0.3, atol=1e-6)
    np.testing.assert_allclose(track.psi[:, K["mouthSmile_R"]], 0.125, atol=1e-6)
    np.testing.assert_allclose(track.psi[:, K["mouthSmile_L"]], 0.0, atol=1e-6)
    for side in ("L", "R"):  # one ARKit shape drives both HACK sides
        np.testing.assert_allclose(track.psi[:, K[f"browInnerUp_{side}"]], 0.5, atol=1e-6)
        np.testing.assert_allclose(track.psi[:, K[f"cheekPuff_{side}"]], 0.25, atol=1e-6)
    assert sorted(track.missing) == ["cheekRaiser_L", "cheekRaiser_R"]
    assert track.psi.max() == pytest.approx(0.55, abs=1e-6)  # TongueOut (0.9) has no HACK shape
    assert track.head_ypr is None  # all-zero head columns: not recorded


def test_live_link_face_head_rotation_and_lost_frames(tmp_path):
    rows, codes = llf_rows(10, head=0.2)
    rows[3] = f"{codes[3]},0"  # tracking lost: Live Link Face writes only the timecode and 0
    rows[4] = f"{codes[4]},0"
    track = read_expressions(write(tmp_path / "take.csv", LLF_HEADER, rows))
    assert len(track) == 8
    np.testing.assert_allclose(track.time, np.delete(np.arange(10) * 2 / 60, [3, 4]), atol=1e-9)
    np.testing.assert_allclose(track.head_ypr, np.tile([0.2, -0.2, 0.0], (8, 1)), atol=1e-9)


def test_arkit_csv_with_prefix_and_seconds(tmp_path):
    header = ["timestamp", "blendShapes.jawOpen", "blendShapes.eyeBlinkRight", "blendShapes.cheekPuff"]
    rows = [f"{100 + 0.02 * i:.3f},{0.1 * (i % 5):.2f},0.5,0.2" for i in range(20)]
    track = read_expressions(write(tmp_path / "arkit.csv", header, rows))
    np.testing.assert_allclose(track.time, 0.02 * np.arange(20), atol=1e-9)
    assert track.fps == pytest.approx(50.0, rel=1e-6)
    np.testing.assert_allclose(track.psi[:, K["jawOpen"]], 0.1 * (np.arange(20) % 5), atol=1e-6)
    np.testing.assert_allclose(track.psi[:, K["eyeBlink_R"]], 0.5, atol=1e-6)
    np.testing.assert_allclose(track.psi[:, [K["cheekPuff_L"], K["cheekPuff_R"]]], 0.2, atol=1e-6)
    assert len(track.missing) == 55 - 4


def test_two_column_csv_keeps_its_zero_rows(tmp_path):
    """Only under Live Link Face's wide header is "<time>,0" a lost frame; a one-shape take keeps its zeros."""
    rows = [f"{i / 30:.6f},{0.0 if i % 3 else 0.4}" for i in range(9)]
    track = read_expressions(write(tmp_path / "jaw.csv", ["time", "jawOpen"], rows))
    assert len(track) == 9
    np.testing.assert_allclose(track.psi[:, K["jawOpen"]], [0.4 if i % 3 == 0 else 0.0 for i in range(9)], atol=1e-7)


def test_hack_named_csv_with_frames_needs_fps(tmp_path):
    path = write(tmp_path / "hack.csv", ["frame", "jawOpen", "mouthPress_L"],
                 [f"{i},{0.01 * i:.2f},0.3" for i in range(10, 16)])
    with pytest.raises(InputError, match="column 'frame' but no time column; give fps"):
        read_expressions(path)
    track = read_expressions(path, fps=25)
    np.testing.assert_allclose(track.time, np.arange(6) / 25, atol=1e-12)
    np.testing.assert_allclose(track.psi[:, K["jawOpen"]], 0.01 * np.arange(10, 16), atol=1e-6)


def test_headerless_csv_and_npy(tmp_path):
    psi = np.random.default_rng(0).uniform(0, 1, (7, 55))
    path = tmp_path / "plain.csv"
    np.savetxt(path, psi, delimiter=",")
    with pytest.raises(InputError, match="plain.csv: a header-less table carries no frame rate; give fps"):
        read_expressions(path)
    track = read_expressions(path, fps=60)
    np.testing.assert_allclose(track.psi, psi, atol=1e-6)
    np.testing.assert_allclose(track.time, np.arange(7) / 60)
    np.savetxt(tmp_path / "short.csv", psi[:, :54], delimiter=",")
    with pytest.raises(InputError, match="short.csv: 54 columns without a header, expected 55"):
        read_expressions(tmp_path / "short.csv", fps=60)
    np.save(tmp_path / "psi.npy", psi.astype(np.float32))
    np.testing.assert_allclose(read_expressions(tmp_path / "psi.npy", fps=30).psi, psi, atol=1e-6)
    np.save(tmp_path / "bad.npy", psi[:, :50])
    with pytest.raises(InputError, match=r"bad.npy: array of shape \(7, 50\), expected expression weights"):
        read_expressions(tmp_path / "bad.npy", fps=30)


@pytest.mark.parametrize("cell, match", [
    ("abc", r"take.csv: column 'JawOpen', line 4: expected a number, found 'abc'"),
    ("45", r"take.csv: column 'JawOpen', line 4: weight 45 outside"),
])
def test_errors_name_file_column_and_line(tmp_path, cell, match):
    rows, _ = llf_rows(5)
    cells = rows[2].split(",")
    cells[LLF_HEADER.index("JawOpen")] = cell
    rows[2] = ",".join(cells)  # line 4 of the file (header is line 1)
    with pytest.raises(InputError, match=match):
        read_expressions(write(tmp_path / "take.csv", LLF_HEADER, rows))


def test_timecode_and_time_errors(tmp_path):
    rows, _ = llf_rows(5)
    rows[1] = "12:21:59:xx," + rows[1].split(",", 1)[1]
    with pytest.raises(InputError, match=r"take.csv: column 'Timecode', line 3: '12:21:59:xx' is not HH:MM:SS:FF"):
        read_expressions(write(tmp_path / "take.csv", LLF_HEADER, rows))
    path = write(tmp_path / "back.csv", ["time", "jawOpen"], ["0.0,0.1", "0.1,0.1", "0.05,0.2"])
    with pytest.raises(InputError, match=r"back.csv: column 'time' must increase, but line 4"):
        read_expressions(path)
    path = write(tmp_path / "none.csv", ["time", "foo", "bar"], ["0.0,1,2", "0.1,1,2"])
    with pytest.raises(InputError, match=r"none.csv: no expression columns found.*Columns: time, foo, bar"):
        read_expressions(path)
    with pytest.raises(InputError, match="missing.csv: file not found"):
        read_expressions(tmp_path / "missing.csv")


@pytest.mark.parametrize("value", ["nan", "inf", "-inf"])
def test_headerless_csv_rejects_non_finite_naming_line_and_column(tmp_path, value):
    psi = np.full((4, 55), 0.2)
    lines = [",".join(f"{v:g}" for v in row) for row in psi]
    cells = lines[2].split(",")
    cells[K["jawOpen"]] = value
    lines[2] = ",".join(cells)  # line 3 of a header-less file
    (tmp_path / "plain.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=rf"plain\.csv: column 'jawOpen', line 3: value is {value}, expected finite"):
        read_expressions(tmp_path / "plain.csv", fps=30)


def test_headerless_csv_with_byte_order_mark_and_ragged_line(tmp_path):
    psi = np.random.default_rng(1).uniform(0, 1, (5, 55)).round(4)
    text = "\n".join(",".join(f"{v:.4f}" for v in row) for row in psi) + "\n"
    (tmp_path / "bom.csv").write_bytes(b"\xef\xbb\xbf" + text.encode())  # Excel's "CSV UTF-8"
    track = read_expressions(tmp_path / "bom.csv", fps=30)
    np.testing.assert_allclose(track.psi, psi, atol=1e-6)
    lines = text.splitlines()
    lines[3] = lines[3].rsplit(",", 1)[0]
    (tmp_path / "ragged.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=r"ragged\.csv: line 4 has 54 cells, expected 55"):
        read_expressions(tmp_path / "ragged.csv", fps=30)
    lines = text.splitlines()
    lines[1] = ",".join(["45"] + lines[1].split(",")[1:])
    (tmp_path / "degrees.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(InputError, match=rf"degrees\.csv: column '{EXPRESSION_NAMES[0]}', line 2: weight 45 outside"):
        read_expressions(tmp_path / "degrees.csv", fps=30)


def test_missing_rate_names_the_callers_key(tmp_path):
    psi = np.full((3, 55), 0.1)
    np.savetxt(tmp_path / "plain.csv", psi, delimiter=",")
    np.save(tmp_path / "psi.npy", psi)
    write(tmp_path / "frames.csv", ["frame", "jawOpen"], ["0,0.1", "1,0.2"])
    for name in ("plain.csv", "psi.npy", "frames.csv"):
        with pytest.raises(InputError, match=rf"{name}: .*give expressions_fps=\.\.\."):
            read_expressions(tmp_path / name, fps_key="expressions_fps")
        with pytest.raises(InputError, match=r"give fps=\.\.\."):  # the default key
            read_expressions(tmp_path / name)


def short_take(path, frames):
    """A Live Link Face take whose timecode frame numbers are ``frames`` (all in one second)."""
    rows = []
    for f in frames:
        values = {name: 0.0 for name in ARKIT}
        values["JawOpen"] = 0.01 * f
        rows.append(",".join([f"09:30:12:{f:02d}.000", "61", *[f"{values[n]:.4f}" for n in ARKIT], *["0.0"] * 9]))
    return write(path, LLF_HEADER, rows)


def test_short_live_link_face_take_needs_timecode_fps(tmp_path):
    path = short_take(tmp_path / "short.csv", range(0, 20))  # 20 frames: 0.8 s at 25 fps, 0.67 s at 30 fps
    with pytest.raises(InputError, match=r"short\.csv: column 'Timecode': .*ambiguous.*give timecode_fps=\.\.\."):
        read_expressions(path)
    for rate in (25, 30):
        track = read_expressions(path, timecode_fps=rate)
        np.testing.assert_allclose(track.time, np.arange(20) / rate, atol=1e-9)
        assert track.fps == pytest.approx(rate)
    # Frame numbers reaching 23: a full second at 24 fps, read without timecode_fps.
    full = read_expressions(short_take(tmp_path / "second.csv", range(0, 24)))
    assert full.fps == pytest.approx(24.0) and full.time[-1] == pytest.approx(23 / 24)


def test_resampled_is_linear_on_a_uniform_grid(tmp_path):
    time = np.array([0.0, 0.1, 0.25, 0.3, 0.5])
    path = write(tmp_path / "uneven.csv", ["time", "jawOpen"], [f"{t},{2 * t:.3f}" for t in time])
    track = read_expressions(path).resampled(20)
    np.testing.assert_allclose(track.time, np.arange(11) / 20, atol=1e-12)
    np.testing.assert_allclose(track.psi[:, K["jawOpen"]], 2 * track.time, atol=1e-6)
    assert track.fps == 20


def test_real_live_link_face_samples(livelinkface_samples):
    for path in livelinkface_samples:
        track = read_expressions(path)
        assert track.psi.shape[1] == 55 and len(track) > 1000, path
        assert track.fps == pytest.approx(30.0, rel=0.01), path  # 60 fps timecode, every other frame
        assert np.all(np.diff(track.time) > 0), path
        assert track.psi.min() >= -0.1 and track.psi.max() <= 1.5, path  # trackers overshoot [0, 1] a little
        assert np.mean((track.psi >= 0) & (track.psi <= 1)) > 0.99, path
        assert sorted(track.missing) == ["cheekRaiser_L", "cheekRaiser_R"], path
        assert track.head_ypr is None, path  # these takes did not record head rotation
        np.testing.assert_array_equal(track.psi[:, K["browInnerUp_L"]], track.psi[:, K["browInnerUp_R"]])
        resampled = track.resampled(30)
        assert len(resampled) == int(np.floor(track.time[-1] * 30 + 1e-9)) + 1
