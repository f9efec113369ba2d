"""Writing files: every output goes through :func:`atomic_path` (a folder through :func:`atomic_folder`), so a
crash never leaves a half-written file or folder.

The data is written to a temporary file beside the target and renamed over it.  Also the one ``.npy``
reader with rank, dtype and finiteness checks.
"""
from __future__ import annotations

import contextlib
import csv
import io
import os
import shutil
import socket
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import numpy as np

from base.errors import InputError, require_file

STAGING_SUFFIX = ".partial"   # a folder being written by atomic_folder


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


def load_npy(path: str | os.PathLike, ndim: int | tuple[int, ...], what: str) -> np.ndarray:
    """Load a ``.npy`` array, checking its rank; ``what`` describes the expected content."""
    path = require_file(path)
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


def require_new_folder(out_dir: Path) -> None:
    """InputError unless ``out_dir`` is absent or an empty folder."""
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise InputError(f"out_dir={out_dir}: already exists and is not an empty folder; give a new one")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def stale_staging(out_dir: Path) -> list[Path]:
    """The staging folders of ``out_dir`` (``.<name>.<host>-<pid>.<random>.partial``) left by a run on this
    machine whose process is gone (killed: SIGKILL, OOM, power loss), which no ``finally`` removed.  A live
    process's, another machine's (shared storage: its pid means nothing here) and older unnamed ones are not."""
    prefix, host = f".{out_dir.name}.", socket.gethostname()
    found = []
    if out_dir.parent.is_dir():
        for path in out_dir.parent.iterdir():
            name = path.name
            if not (name.startswith(prefix) and name.endswith(STAGING_SUFFIX)) or not path.is_dir():
                continue
            owner = name[len(prefix):-len(STAGING_SUFFIX)].rpartition(".")[0]   # mkdtemp's part has no "."
            who, _, pid = owner.rpartition("-")
            if who == host and pid.isdigit() and not _alive(int(pid)):
                found.append(path)
    return sorted(found)


@contextlib.contextmanager
def atomic_folder(out_dir: Path, announce=None) -> Iterator[Path]:
    """A staging folder beside ``out_dir`` (absent or empty), renamed to it with a normal folder's mode when
    the block succeeds and removed otherwise: :func:`atomic_path` for a folder.  The staging folders an
    earlier, killed run left for the same ``out_dir`` (:func:`stale_staging`) are removed first, each named
    through ``announce``."""
    require_new_folder(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    for stale in stale_staging(out_dir):
        shutil.rmtree(stale, ignore_errors=True)
        if announce is not None:
            announce(f"{out_dir}: removed {stale.name}, the unfinished output of a run that was killed")
    owner = f"{socket.gethostname()}-{os.getpid()}"
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.{owner}.", suffix=STAGING_SUFFIX, dir=out_dir.parent))
    try:
        yield staging
        if out_dir.is_dir():
            out_dir.rmdir()  # empty (checked above)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(staging, 0o777 & ~umask)  # mkdtemp makes 0700
        os.replace(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
