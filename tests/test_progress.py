"""base.progress: a line now and then where there is no terminal."""
from __future__ import annotations

import io

import base.progress as progress_module
from base.progress import LineProgress, progress_bar


def test_lines_come_at_the_interval_and_once_at_the_end(monkeypatch):
    clock = iter(float(t) for t in range(0, 1000))
    monkeypatch.setattr(progress_module.time, "perf_counter", lambda: next(clock))
    out = io.StringIO()
    bar = LineProgress(range(100), desc="train", unit="step", interval=30.0, stream=out)
    for i in bar:
        if i == 50:
            bar.set_postfix({"loss": "0.25"})
    lines = out.getvalue().splitlines()
    # the clock ticks a second per reading (one per update, one per printed line): lines at steps 30, 59, 88, 100
    assert [line.split()[1] for line in lines] == ["30/100", "59/100", "88/100", "100/100"], lines
    assert lines[0].startswith("train: 30/100 step (")
    assert lines[-1].endswith("loss=0.25")


def test_a_short_loop_prints_nothing():
    out = io.StringIO()
    with LineProgress(total=5, desc="takes", interval=30.0, stream=out) as bar:
        for _ in range(5):
            bar.update(1)
    assert out.getvalue() == ""


def test_no_terminal_no_bar(capsys):
    bar = progress_bar(range(3), desc="x")  # pytest captures standard error: not a terminal
    assert isinstance(bar, LineProgress) and list(bar) == [0, 1, 2]
    assert capsys.readouterr().err == ""
