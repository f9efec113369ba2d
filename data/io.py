"""File I/O shared by every tool: atomic writes, CSV tables, tau tracks.

Conventions owned here:
- Every file the project writes goes through :func:`atomic_path`: the data is
  written to a temporary file beside the target and renamed over it, so a
  crash never leaves a half-written output.
- Bad input raises :class:`InputError`, whose message names the file, the
  column or frame, and what was expected.
- A *tau track* is the larynx slide over time: ``tau`` in UV units of the
  larynx map (positive = up the neck, see ``models.rig``), sampled at an
  explicit ``fps``.  On disk it is a CSV with a ``tau`` column and a ``time``
  (seconds) or ``frame`` column (plus ``fps``), or a ``.npy`` vector with the
  fps given by the caller (who names its config key for it, ``fps_key``, in
  the error when it is missing).
"""
from __future__ import annotations

import contextlib
import csv
import io
import os
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Mapping, Sequence

import numpy as np


class InputError(ValueError):
    """Bad user input.  The message names the file, the column or frame, and what was expected."""


# --------------------------------------------------------------------------- writing


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it over ``path`` if the block succeeds.

    The temporary name keeps the target's suffix so that libraries choosing a
    format by extension (OpenCV, numpy, matplotlib) behave as for the target.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}", dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)  # mkstemp makes 0600; give the file a normal mode
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()


def write_text(path: str | os.PathLike, text: str) -> None:
    with atomic_path(path) as tmp:
        tmp.write_text(text)


def fresh_output_folder(folder: str | os.PathLike, patterns: Sequence[str], key: str) -> Path:
    """Create ``folder`` (and parents) for a run's many output files; InputError (naming ``key``, the
    config key that chose it) if it already holds files matching ``patterns`` (globs) from an earlier run:
    a reader of the folder would mix the two runs."""
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise InputError(f"{key}={folder}: not a folder")
    stale = sorted({p.name for pattern in patterns for p in folder.glob(pattern)}) if folder.is_dir() else []
    if stale:
        raise InputError(f"{key}={folder}: already holds {len(stale)} output file(s) of an earlier run "
                         f"({', '.join(stale[:3])}{', ...' if len(stale) > 3 else ''}); give a new or empty folder")
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def save_npy(path: str | os.PathLike, array: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, array)


def save_npz(path: str | os.PathLike, compressed: bool = True, **arrays: np.ndarray) -> None:
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            (np.savez_compressed if compressed else np.savez)(f, **arrays)


def write_csv(path: str | os.PathLike, columns: Mapping[str, Sequence], float_format: str = "%.6g") -> None:
    """Write equal-length columns to a CSV file with a header row, atomically."""
    names = list(columns)
    arrays = [np.asarray(columns[n]) for n in names]
    lengths = {len(a) for a in arrays}
    if len(lengths) > 1:
        raise ValueError(f"write_csv({path}): columns have different lengths {dict(zip(names, map(len, arrays)))}")

    def cell(value) -> str:
        if isinstance(value, (float, np.floating)):
            return float_format % value
        return str(value)

    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(names)
    for row in zip(*arrays):
        writer.writerow([cell(v) for v in row])
    write_text(path, buffer.getvalue())


def figure(**subplots):
    """A matplotlib figure and its axes (``plt.subplots(**subplots)``) on the file-only Agg backend."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(**subplots)


def save_figure(fig, path: str | os.PathLike, dpi: int = 110) -> None:
    """Save a figure atomically (format from the suffix) and close it."""
    import matplotlib.pyplot as plt

    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi)
    plt.close(fig)


# --------------------------------------------------------------------------- reading


class CsvTable:
    """A CSV file (UTF-8, with or without a byte-order mark) read as text; numeric access with precise errors.

    The first row is the header, unless ``columns`` names the columns of a
    header-less file (every row is then data).  ``skip_row(cells) -> bool``
    drops data rows before validation (e.g. a tracker's "lost" rows); their
    line numbers are kept in ``skipped_lines``.  Errors name the file, the
    column and the line of the file.
    """

    def __init__(self, path: str | os.PathLike, skip_row=None, columns: Sequence[str] | None = None):
        self.path = Path(path)
        if not self.path.is_file():
            raise InputError(f"{self.path}: file not found")
        with open(self.path, newline="", encoding="utf-8-sig") as f:
            numbered = [(n + 1, row) for n, row in enumerate(csv.reader(f)) if row and any(c.strip() for c in row)]
        if columns is None:
            if not numbered:
                raise InputError(f"{self.path}: empty file, expected a header row and data rows")
            self.header = [h.strip() for h in numbered[0][1]]
            body = numbered[1:]
            where = "below the header"
            width = "the header has"
        else:
            self.header = list(columns)
            body = numbered
            where = "(a header-less table)"
            width = "expected"
        self.skipped_lines = [n for n, row in body if skip_row is not None and skip_row(row)]
        body = [(n, row) for n, row in body if skip_row is None or not skip_row(row)]
        if not body:
            raise InputError(f"{self.path}: no data rows {where}")
        self.lines = [n for n, _ in body]
        self.rows = [row for _, row in body]
        for n, row in body:
            if len(row) != len(self.header):
                raise InputError(f"{self.path}: line {n} has {len(row)} cells, {width} {len(self.header)}")
        self._index = {name: i for i, name in enumerate(self.header)}

    def __len__(self) -> int:
        return len(self.rows)

    def keep_rows(self, keep: np.ndarray) -> None:
        """Keep only the data rows where ``keep`` [rows] is True (their line numbers go with them)."""
        self.rows = [row for row, k in zip(self.rows, keep) if k]
        self.lines = [line for line, k in zip(self.lines, keep) if k]

    def has(self, name: str) -> bool:
        return name in self._index

    def text(self, name: str) -> list[str]:
        if name not in self._index:
            raise InputError(f"{self.path}: no column '{name}' (columns: {', '.join(self.header)})")
        j = self._index[name]
        return [row[j].strip() for row in self.rows]

    def numeric(self, name: str) -> np.ndarray:
        """Column ``name`` as float64; a non-number names its row."""
        values = self.text(name)
        out = np.empty(len(values))
        for i, v in enumerate(values):
            try:
                out[i] = float(v)
            except ValueError:
                raise InputError(
                    f"{self.path}: column '{name}', line {self.lines[i]}: expected a number, found '{v}'"
                ) from None
            if not np.isfinite(out[i]):
                raise InputError(f"{self.path}: column '{name}', line {self.lines[i]}: value is {v}, expected finite")
        return out


def load_npy(path: str | os.PathLike, ndim: int | tuple[int, ...], what: str) -> np.ndarray:
    """Load a ``.npy`` array, checking its rank; ``what`` describes the expected content."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        array = np.load(path, allow_pickle=False)
    except (ValueError, OSError) as e:
        raise InputError(f"{path}: not a readable .npy array ({e}); expected {what}") from None
    ndims = (ndim,) if isinstance(ndim, int) else ndim
    if array.ndim not in ndims:
        raise InputError(f"{path}: array of shape {array.shape}, expected {what}")
    if not np.issubdtype(array.dtype, np.number):
        raise InputError(f"{path}: array of dtype {array.dtype}, expected numbers ({what})")
    bad = ~np.isfinite(array)
    if bad.any():
        first = np.argwhere(bad)[0]
        raise InputError(f"{path}: non-finite value at index {tuple(first.tolist())}; expected {what}")
    return array


# --------------------------------------------------------------------------- tau tracks


@dataclass
class TauTrack:
    """Larynx slide over time.

    tau:  [T] UV units of the larynx map, positive = up the neck.
    time: [T] seconds, increasing.
    fps:  nominal frame rate (frames per second).
    """

    tau: np.ndarray
    time: np.ndarray
    fps: float
    source: str = ""

    def __post_init__(self) -> None:
        self.tau = np.asarray(self.tau, dtype=np.float64)
        self.time = np.asarray(self.time, dtype=np.float64)
        if self.tau.shape != self.time.shape or self.tau.ndim != 1:
            raise ValueError(f"TauTrack {self.source}: tau {self.tau.shape} and time {self.time.shape} must be equal 1-D")
        if not self.fps > 0:
            raise ValueError(f"TauTrack {self.source}: fps must be positive, got {self.fps}")

    def __len__(self) -> int:
        return len(self.tau)


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


def as_list(value) -> list:
    """A config value that may be one item or a list (``at=2.0``, ``at=[1,2]``, ``inputs=a.csv``) as a list.

    None is the empty list; a string is one item (not its characters).
    """
    if value is None:
        return []
    if isinstance(value, (str, bytes)) or not isinstance(value, Sequence):
        return [value]
    return list(value)


def split_by_file(items: Sequence, val_fraction: float, seed: int, what: str = "file") -> tuple[list, list]:
    """Split recordings by file: (train, validation) lists of ``items``, no item in both.

    ``round(val_fraction * len(items))`` items are held out, at least one and at most all but one;
    which ones is a permutation drawn from ``seed`` (deterministic), each list keeps the input order.
    ``what`` names the items in the error for fewer than two.
    """
    if len(items) < 2:
        raise InputError(f"{len(items)} {what}(s); need at least 2 to split into training and validation")
    if not 0 < val_fraction < 1:
        raise InputError(f"val_fraction must be in (0, 1), got {val_fraction}")
    count = min(len(items) - 1, max(1, int(round(val_fraction * len(items)))))
    held_out = set(np.random.default_rng(seed).permutation(len(items))[:count].tolist())
    return ([x for i, x in enumerate(items) if i not in held_out], [x for i, x in enumerate(items) if i in held_out])


def read_tau_track(path: str | os.PathLike, fps: float | None = None,
                   min_confidence: float | None = None, fps_key: str = "fps") -> TauTrack:
    """Read a tau track from CSV (``tau`` + ``time`` or ``frame`` [+ ``fps``]) or ``.npy``.

    ``fps`` is the frame rate of a file that carries none: a ``.npy``, a CSV
    with a ``frame`` but no ``time`` or ``fps`` column, or a one-row CSV; a
    file's own rate (its ``fps`` column, else its ``time`` stamps) wins.
    ``fps_key`` is the caller's name for that setting (its config key), named
    in the error when the rate is needed and missing.  With
    ``min_confidence``, rows of a CSV whose ``confidence`` column (the
    tracker's) is below it are dropped: the track then has gaps in time.
    Files without a ``confidence`` column are read whole.  A tracker CSV
    whose ``tau`` is NaN on every row (``tau_px`` only: no calibration) is
    reported as such.
    """
    path = Path(path)
    if path.suffix.lower() == ".npy":
        tau = load_npy(path, (1, 2), "a tau track [T] or [T,1]")
        if tau.ndim == 2:
            if tau.shape[1] != 1:
                raise InputError(f"{path}: array of shape {tau.shape}, expected a tau track [T] or [T,1]")
            tau = tau[:, 0]
        if fps is None:
            raise InputError(f"{path}: a .npy tau track carries no frame rate; give {fps_key}=...")
        return TauTrack(tau, np.arange(len(tau)) / fps, float(fps), str(path))
    if path.suffix.lower() != ".csv":
        raise InputError(f"{path}: unsupported tau track format '{path.suffix}', expected .csv or .npy")

    table = CsvTable(path)
    if min_confidence is not None and table.has("confidence"):
        # Before parsing tau: a tracker writes NaN positions for frames it has lost (confidence 0).
        keep = table.numeric("confidence") >= min_confidence
        if keep.sum() < 2:
            raise InputError(f"{path}: fewer than 2 rows with confidence >= {min_confidence:g}")
        table.keep_rows(keep)
    if table.has("tau") and table.has("tau_px") and all(v.lower() == "nan" for v in table.text("tau")):
        raise InputError(
            f"{path}: column 'tau' is NaN on every row: the track has no calibration (tau_px only); "
            f"run python -m motion.track with px_per_tau=<pixels per tau unit>, or with cm_per_px=... kernel=rig "
            f"(px_per_tau=auto from the rig)"
        )
    tau = table.numeric("tau")
    rate = None
    if table.has("fps"):
        values = table.numeric("fps")
        if not np.allclose(values, values[0]) or values[0] <= 0:
            raise InputError(f"{path}: column 'fps' must hold one positive value, found {np.unique(values)[:5]}")
        rate = float(values[0])
    if table.has("time"):
        time = table.numeric("time")
        check_increasing(time, table, "time")
        if rate is None:
            if len(time) >= 2:
                rate = estimate_fps(time)
            elif fps is not None:
                rate = fps
            else:
                raise InputError(f"{path}: one row only; give {fps_key}=... to know its frame rate")
    elif table.has("frame"):
        frame = table.numeric("frame")
        check_increasing(frame, table, "frame")
        rate = rate if rate is not None else fps
        if rate is None:
            raise InputError(f"{path}: column 'frame' without a 'time' or 'fps' column; give {fps_key}=...")
        time = frame / rate
    else:
        raise InputError(f"{path}: expected a 'time' (seconds) or 'frame' column beside 'tau'")
    return TauTrack(tau, time, float(rate), str(path))


def write_tau_track(path: str | os.PathLike, track: TauTrack, **extra: Sequence) -> None:
    """Write ``frame,time,tau[,extra...],fps`` atomically (CSV) or the tau vector (``.npy``)."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        save_npy(path, track.tau.astype(np.float32))
        return
    columns = {"frame": np.arange(len(track)), "time": track.time, "tau": track.tau}
    columns.update(extra)
    columns["fps"] = np.full(len(track), track.fps)
    write_csv(path, columns, float_format="%.9g")  # time of an hour-long take to 1e-5 s


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
    count = int(np.floor((stop - start) * fps + 1e-9)) + 1
    grid = start + np.arange(max(count, 0)) / fps
    flat = values.reshape(len(time), -1)
    out = np.stack([np.interp(grid, time, flat[:, k]) for k in range(flat.shape[1])], axis=1)
    return grid, out.reshape((len(grid),) + values.shape[1:]).astype(values.dtype if values.dtype.kind == "f" else np.float64)
