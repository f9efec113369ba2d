"""infer.py on bad capture files: one line naming the file and the row or column, exit status 2, and
nothing left in out_dir.  The files are the ten kinds a user hands in by mistake."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from base.cli import compose_config
from base.errors import InputError
from tests.test_expressions import LLF_HEADER, llf_rows

REPO = Path(__file__).resolve().parents[1]


def llf(path: Path, rows: list[str], header: list[str] = LLF_HEADER) -> Path:
    path.write_text(",".join(header) + "\n" + "".join(row + "\n" for row in rows))
    return path


def bad_files(tmp: Path) -> dict[str, tuple[Path, str]]:
    """name -> (file, the error it must give: a regex naming the file and the row or column)."""
    rows, _ = llf_rows(25)
    files = {}
    (tmp / "empty.csv").write_text("")
    files["empty file"] = (tmp / "empty.csv", r"empty\.csv: empty file")
    files["header only"] = (llf(tmp / "header.csv", []), r"header\.csv: no data rows below the header")
    keep = LLF_HEADER[:2] + LLF_HEADER[2:20] + LLF_HEADER[-9:]  # 18 of the 52 ARKit columns
    index = [LLF_HEADER.index(c) for c in keep]
    partial = [",".join(row.split(",")[i] for i in index) for row in rows]
    files["missing columns"] = (llf(tmp / "partial.csv", partial, keep),
                                r"partial\.csv: no column for 3\d of the 55 expressions .*allow_missing=true")
    text = list(rows)
    text[7] = text[7].replace("0.300000", "abc", 1)
    files["text in a number"] = (llf(tmp / "text.csv", text), r"text\.csv: column 'JawOpen', line 9: expected a number")
    nan = list(rows)
    nan[3] = nan[3].replace("0.300000", "nan", 1)
    files["NaN"] = (llf(tmp / "nan.csv", nan), r"nan\.csv: column 'JawOpen', line 5: value is nan, expected finite")
    backwards = list(rows)
    backwards[10], backwards[11] = backwards[11], backwards[10]
    files["timecodes backwards"] = (llf(tmp / "back.csv", backwards), r"back\.csv: column 'Timecode' must increase, "
                                                                      r"but line 13")
    truncated = list(rows)
    truncated[-1] = ",".join(truncated[-1].split(",")[:30])
    files["truncated last row"] = (llf(tmp / "cut.csv", truncated), r"cut\.csv: line 26 has 30 cells, the header has")
    (tmp / "take.txt").write_text((tmp / "text.csv").read_text())
    files["wrong extension"] = (tmp / "take.txt", r"take\.txt: unsupported expression format '\.txt'")
    (tmp / "binary.csv").write_bytes(bytes(range(256)) * 8)
    files["binary file"] = (tmp / "binary.csv", r"binary\.csv: not a text CSV")
    (tmp / "other.csv").write_text("time,speed,temperature\n0.0,1.0,20\n0.1,1.2,21\n")
    files["unrelated columns"] = (tmp / "other.csv", r"other\.csv: no expression columns found")
    return files


BAD = ["empty file", "header only", "missing columns", "text in a number", "NaN", "timecodes backwards",
       "truncated last row", "wrong extension", "binary file", "unrelated columns"]


@pytest.mark.parametrize("kind", BAD)
def test_bad_capture_is_named_and_nothing_is_written(tmp_path, kind):
    from infer import run

    path, message = bad_files(tmp_path)[kind]
    out = tmp_path / "out"
    with pytest.raises(InputError, match=message):
        run(compose_config("infer", [f"expressions={path}", f"out_dir={out}", "checkpoint=none", "head2neck=none"]))
    assert not out.exists()
    assert not any(p.name.endswith(".partial") for p in tmp_path.iterdir())


def test_bad_capture_exits_with_status_2_and_one_line(tmp_path):
    path, _ = bad_files(tmp_path)["binary file"]
    out = tmp_path / "out"
    result = subprocess.run([sys.executable, "infer.py", f"expressions={path}", f"out_dir={out}"], cwd=REPO,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: ") and "binary.csv" in lines[0], result.stderr
    assert not out.exists()


def test_missing_columns_run_when_allowed(tmp_path):
    from infer import run

    path, _ = bad_files(tmp_path)["missing columns"]
    out = tmp_path / "out"
    [row] = run(compose_config("infer", [f"expressions={path}", f"out_dir={out}", "checkpoint=none",
                                         "head2neck=none", "allow_missing=true", "plot=false"]))
    assert row["status"] == "ok" and row["frames"] == 25
    assert (out / "params.npz").is_file()


@pytest.mark.parametrize("overrides, message", [
    (["mesh_format=stl"], r"mesh_format=stl: expected one of ply, obj"),
    (["export=[obj]"], r"export=\[.obj.\]: expected some of glb, mp4, html, fbx, usd"),
    (["usd_format=abc"], r"usd_format=abc: expected one of usdc, usda, usdz"),
    (["usd_units=mm"], r"usd_units=mm: expected one of cm, m"),
    (["fbx_units=mm"], r"fbx_units=mm: expected one of cm, m"),
    (["workers=0"], r"workers=0: expected at least 1"),
    (["swallow_template=t.csv"], r"swallow_template=t\.csv needs swallow_at"),
    (["frames=3"], r"Key 'frames' not in 'InferConfig'"),
    (["eta=big"], r"eta=big.*could not be converted to Float"),
])
def test_bad_settings_are_named(tmp_path, overrides, message):
    from infer import run

    with pytest.raises(InputError, match=message):
        run(compose_config("infer", [f"out_dir={tmp_path / 'out'}", *overrides]))
    assert not (tmp_path / "out").exists()


def test_used_out_dir_is_refused(tmp_path):
    from infer import run

    out = tmp_path / "out"
    out.mkdir()
    (out / "params.npz").write_text("an earlier run")
    with pytest.raises(InputError, match=r"out_dir=.*out: already exists and is not an empty folder"):
        run(compose_config("infer", [f"out_dir={out}", "checkpoint=none", "head2neck=none"]))
    assert [p.name for p in out.iterdir()] == ["params.npz"]
