"""Tau tracks: the larynx slide over time, and their files.

A *tau track* is ``tau`` in UV units of the larynx map (positive = up the neck, see ``models.rig``),
sampled at an explicit ``fps``.  On disk it is a CSV with a ``tau`` column and a ``time`` (seconds) or
``frame`` column (plus ``fps``), or a ``.npy`` vector with the fps given by the caller (who names its
config key for it, ``fps_key``, in the error when it is missing).
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError
from base.files import load_npy, save_npy, write_csv
from base.tables import CsvTable
from base.timebase import check_increasing, estimate_fps


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
            raise ValueError(f"TauTrack {self.source}: tau {self.tau.shape} and time {self.time.shape} must be "
                             f"equal 1-D")
        if not self.fps > 0:
            raise ValueError(f"TauTrack {self.source}: fps must be positive, got {self.fps}")

    def __len__(self) -> int:
        return len(self.tau)


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
