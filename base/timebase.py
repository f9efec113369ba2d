"""Time axes: every recording's frames carry seconds and an explicit ``fps``.

The one place that reads a time axis from a table (timecodes, time stamps, frame numbers), estimates a
frame rate, checks that time increases, and resamples onto a uniform grid.
"""
from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from base.errors import InputError
from base.tables import CsvTable

TIME_COLUMNS = ("time", "timestamp", "seconds", "time_s")


def row_name(lines: list[int] | None, i: int) -> str:
    """Where data row ``i`` is: a line of a CSV file, or a row of an array."""
    return f"line {lines[i]}" if lines is not None else f"row {i}"


def estimate_fps(time: np.ndarray) -> float:
    """Frame rate from sample times (s): 1 / median step, rounded to 1e-3 (29.97 stays 29.97)."""
    return round(float(1.0 / np.median(np.diff(time))), 3)


def check_increasing(time: np.ndarray, table: CsvTable, column: str) -> None:
    """Raise InputError naming the file and line where ``column`` (values ``time``, one per data row of
    ``table``) does not strictly increase."""
    steps = np.diff(time)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0)) + 1
        raise InputError(
            f"{table.path}: column '{column}' must increase, but line {table.lines[i]} ({time[i]:g}) "
            f"is not after line {table.lines[i - 1]} ({time[i - 1]:g})"
        )


def resample_uniform(time: np.ndarray, values: np.ndarray, fps: float, start: float | None = None,
                     stop: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Linearly resample ``values`` [T, ...] given at ``time`` [T] onto a uniform grid at ``fps``.

    Returns (new_time [T'], new_values [T', ...]).  The grid runs from ``start``
    (default ``time[0]``) while it does not pass ``stop`` (default ``time[-1]``).
    """
    time = np.asarray(time, dtype=np.float64)
    values = np.asarray(values)
    start = time[0] if start is None else start
    stop = time[-1] if stop is None else stop
    count = int(np.floor((stop - start) * fps + 1e-4)) + 1  # stamps printed to ~1e-9 s: within 1e-4 frame
    grid = start + np.arange(max(count, 0)) / fps
    flat = values.reshape(len(time), -1)
    out = np.stack([np.interp(grid, time, flat[:, k]) for k in range(flat.shape[1])], axis=1)
    dtype = values.dtype if values.dtype.kind == "f" else np.float64
    return grid, out.reshape((len(grid),) + values.shape[1:]).astype(dtype)


def parse_timecode(codes: list[str], path: Path, rate: float | None = None,
                   lines: list[int] | None = None) -> np.ndarray:
    """Seconds from ``HH:MM:SS:FF[.fff]`` timecodes.

    The timecode rate (frames per second of ``FF``) is ``rate`` if given, else
    the smallest standard rate above the largest frame number seen.  A take
    whose frame numbers all stay below 23 (under one second) fits every
    standard rate: that is an InputError asking for ``timecode_fps=...``.
    """
    parts = []
    for i, code in enumerate(codes):
        m = re.fullmatch(r"(\d+):(\d+):(\d+)[:;](\d+(?:\.\d+)?)", code)
        if not m:
            raise InputError(f"{path}: column 'Timecode', {row_name(lines, i)}: '{code}' is not HH:MM:SS:FF.fff")
        parts.append([float(g) for g in m.groups()])
    hms = np.array(parts)
    if rate is None:
        top = np.floor(hms[:, 3]).max()
        if top < 23:
            raise InputError(
                f"{path}: column 'Timecode': frame numbers only reach {top:g}, so the timecode rate is ambiguous "
                f"(24, 25, 30, ... fps all fit a take under one second); give timecode_fps=..."
            )
        rate = next((r for r in (24, 25, 30, 48, 50, 60, 120) if r > top), None)
        if rate is None:
            raise InputError(f"{path}: timecode frame {top:g} exceeds 120 fps; give timecode_fps=...")
    seconds = hms[:, 0] * 3600 + hms[:, 1] * 60 + hms[:, 2] + hms[:, 3] / rate
    seconds = np.where(seconds < seconds[0] - 43200, seconds + 86400, seconds)  # across midnight
    return seconds - seconds[0]


def time_axis(table: CsvTable, fps: float | None, timecode_fps: float | None = None,
              fps_key: str = "fps") -> tuple[np.ndarray, float]:
    """The time axis of a recording's table: (seconds from the first row [T], fps).

    From a ``Timecode`` column (Live Link Face, ``HH:MM:SS:FF[.fff]``), a time column (``time``,
    ``timestamp``, ``seconds``, ``time_s``), a ``frame`` column with ``fps``, or the row index with
    ``fps``.  The rate is ``fps`` if given, else estimated from the stamps; ``fps_key`` is the caller's
    config key for it, named in errors.  Time must strictly increase (the error names the line).
    """
    path = table.path
    lower = {h.lower(): h for h in table.header}
    if "timecode" in lower:
        column = lower["timecode"]
        time = parse_timecode(table.text(column), path, timecode_fps, table.lines)
    elif any(c in lower for c in TIME_COLUMNS):
        column = next(lower[c] for c in TIME_COLUMNS if c in lower)
        time = table.numeric(column)
        time = time - time[0]
    elif "frame" in lower:
        if fps is None:
            raise InputError(f"{path}: column 'frame' but no time column; give {fps_key}=...")
        column = lower["frame"]
        frame = table.numeric(column)
        time = (frame - frame[0]) / fps
    else:
        if fps is None:
            raise InputError(f"{path}: no 'Timecode', 'time' or 'frame' column; give {fps_key}=...")
        column = None
        time = np.arange(len(table)) / fps
    if column is not None:
        check_increasing(time, table, column)
    if fps is None:
        if len(time) < 2:
            raise InputError(f"{path}: one row only; give {fps_key}=...")
        fps = estimate_fps(time)
    return time, float(fps)


# The gap rule (docs/conventions.md, "Gaps"): recorded frames more than GAP_SECONDS apart are a gap.  The grid
# points inside a gap repeat the last grid point before it (every value held, the larynx model's tau too), and
# the frames after it start afresh (a recurrent model restarts its state there).  Causal: a point in a gap
# needs nothing after it, so a live stream pays nothing for a gap when the frame after it arrives.  Shared by
# infer.py (motion.pipeline.animate) and the live receiver (motion.live.stream).  0.25 s: a few lost datagrams
# (interpolated over, at most 8 frames at 30 fps run when the next frame arrives) against a lost face.
GAP_SECONDS = 0.25
GRID_TOLERANCE = 1e-4  # frames: stamps printed to ~1e-9 s land on the grid within it


def last_grid_index(t: float, fps: float) -> int:
    """The last point ``k`` of the grid ``k / fps`` at or before ``t`` (s), within :data:`GRID_TOLERANCE`."""
    return int(np.floor(t * fps + GRID_TOLERANCE))


def first_grid_index(t: float, fps: float) -> int:
    """The first point ``k`` of the grid ``k / fps`` at or after ``t`` (s), within :data:`GRID_TOLERANCE`."""
    return int(np.ceil(t * fps - GRID_TOLERANCE))


def grid_segments(time: np.ndarray, fps: float, gap: float = GAP_SECONDS) -> tuple[np.ndarray, np.ndarray]:
    """The gap rule on :func:`resample_uniform`'s grid from ``time[0]``: (segment [T'] int, the index of the
    run of frames no more than ``gap`` apart that each grid point belongs to; held [T'] bool, the points
    inside a gap, which repeat the point before them)."""
    time = np.asarray(time, dtype=np.float64) - float(time[0])
    count = last_grid_index(float(time[-1]), fps) + 1
    segment = np.zeros(count, dtype=np.int64)
    held = np.zeros(count, dtype=bool)
    for s, k in enumerate(np.flatnonzero(np.diff(time) > gap) + 1, start=1):
        start = max(last_grid_index(float(time[k - 1]), fps) + 1, 0)  # first point after the earlier frame
        resume = first_grid_index(float(time[k]), fps)
        held[start:resume] = True
        segment[start:] = s
    return segment, held


def fill_held(values: np.ndarray, held: np.ndarray) -> np.ndarray:
    """``values`` [T, ...] with every ``held`` point replaced by the last point before it that is not held."""
    source = np.where(held, 0, np.arange(len(held)))
    return np.asarray(values)[np.maximum.accumulate(source)]


def resample_held(time: np.ndarray, values: np.ndarray, fps: float,
                  gap: float = GAP_SECONDS) -> tuple[np.ndarray, np.ndarray]:
    """:func:`resample_uniform` under the gap rule (:func:`grid_segments`): each run of frames interpolated on
    its own, the points inside a gap held."""
    time = np.asarray(time, dtype=np.float64)
    values = np.asarray(values)
    segment, held = grid_segments(time, fps, gap)
    grid = time[0] + np.arange(len(segment)) / fps
    flat = values.reshape(len(time), -1)
    out = np.zeros((len(grid), flat.shape[1]), dtype=np.float64)
    bounds = np.concatenate([[0], np.flatnonzero(np.diff(time) > gap) + 1, [len(time)]])
    for s in range(len(bounds) - 1):
        a, b = bounds[s], bounds[s + 1]
        points = (segment == s) & ~held
        out[points] = np.stack([np.interp(grid[points], time[a:b], flat[a:b, k]) for k in range(flat.shape[1])],
                               axis=1)
    out = fill_held(out, held)
    dtype = values.dtype if values.dtype.kind == "f" else np.float64
    return grid, out.reshape((len(grid),) + values.shape[1:]).astype(dtype)
