"""Expression/larynx pairs: the captured training data of the expression -> larynx transformer.

A *pair file* is an ``.npz`` holding one recording:
- ``psi`` [T,55]: expression weights in ``data.expressions.EXPRESSION_NAMES`` order;
- ``tau`` [T]: larynx slide in UV units of the larynx map, + = up the neck (``data.tau_track``);
- ``fps``: frames per second of both (a scalar);
- optional ``subject`` (a string naming the person), ``take`` (a string naming the recording the
  file was cut from), ``eta`` (larynx size, scalar) and ``time`` [T] (seconds on the expression
  recording's clock, informative only).

A *pairs folder* holds many such files; :func:`split_by_take` splits it into training and validation
**by take**, so clips cut from one recording are never on both sides.  A file without ``take`` belongs
to the take its name gives without a trailing clip number (:func:`take_from_name`: ``anna_take2_clip07``
and ``anna_take2_08`` are take ``anna_take2``; ``take3`` is ``take3``).

Capture workflow: the larynx tracker writes a tau track (CSV ``frame,time,x_px,y_px,tau_px,tau,
confidence``) and the face capture an expression recording (any format ``read_expressions``
reads); ``python -m data.pairs track=track.csv expressions=take.csv out=pair.npz`` aligns them by
time on their overlap, resampled to one rate::

    python -m data.pairs track=track.csv expressions=take.csv out=pairs/take1.npz \\
        [fps=30] [offset=0.25] [subject=anna] [min_confidence=0.3] [track_fps=..] [expressions_fps=..] \\
        [timecode_fps=..]

``offset`` (seconds) is added to the track's time (a tracker that started 0.25 s after the face
capture needs ``offset=0.25``); ``fps`` is the pair's (output) rate, by default the expression
recording's.  The inputs' own rates, where the files carry none, are ``track_fps`` (a ``.npy`` track or
a CSV without ``time``/``fps`` columns), ``expressions_fps`` (header-less or ``.npy`` expressions) and
``timecode_fps`` (a Live Link Face timecode too short to tell its rate).
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from base.errors import InputError
from base.files import save_npz
from base.timebase import resample_uniform
from data.expressions import EXPRESSION_NAMES, NUM_EXPRESSIONS, ExpressionTrack, check_weights, read_expressions
from data.splits import split_by_file
from data.tau_track import TauTrack, read_tau_track


@dataclass
class LarynxSequence:
    """One recording: psi [T,55] float32, tau [T] float32 (UV units), both at ``fps``.

    ``subject`` names the person (None if unknown); ``eta`` is the larynx size if known; ``take`` names
    the recording the sequence was cut from (None: the sequence is a recording of its own, ``name``).
    """

    psi: np.ndarray
    tau: np.ndarray
    fps: float
    subject: str | None
    name: str
    eta: float | None = None
    take: str | None = None

    def __post_init__(self) -> None:
        if self.take is None:
            self.take = self.name

    def __len__(self) -> int:
        return len(self.psi)

    def resampled(self, fps: float) -> LarynxSequence:
        """The same recording linearly resampled to ``fps``."""
        if abs(fps - self.fps) < 1e-9 * fps:
            return self
        time = np.arange(len(self)) / self.fps
        _, psi = resample_uniform(time, self.psi, fps)
        _, tau = resample_uniform(time, self.tau, fps)
        return LarynxSequence(psi.astype(np.float32), tau.astype(np.float32), float(fps), self.subject, self.name,
                              self.eta, self.take)


# --------------------------------------------------------------------------- pair files


def _scalar(data, key: str, path: Path) -> float:
    value = np.asarray(data[key])
    if value.size != 1 or not np.issubdtype(value.dtype, np.number) or not np.isfinite(value).all():
        raise InputError(f"{path}: '{key}' is {value!r}, expected one finite number")
    return float(value.reshape(()))


def take_from_name(stem: str) -> str:
    """The take a pair file belongs to by its name: the stem without a trailing clip number
    (``anna_take2_clip07``, ``anna_take2-08`` -> ``anna_take2``; ``take3`` stays ``take3``)."""
    take = re.sub(r"[_\-. ]+(clip|part|seg|segment|chunk|piece|window)?[_\-. ]*\d+$", "", stem, flags=re.IGNORECASE)
    return take or stem


def _name(data, key: str, path: Path) -> str | None:
    value = np.asarray(data[key])
    if value.dtype.kind not in "US" or value.size != 1:
        raise InputError(f"{path}: '{key}' is {value!r}, expected a name (string)")
    return str(value.reshape(())) or None


def load_pair(path: str | os.PathLike) -> LarynxSequence:
    """Read and validate a pair file (its take: the ``take`` entry, else :func:`take_from_name`)."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        data = dict(np.load(path, allow_pickle=False))
    except Exception as e:  # numpy raises several types for a damaged archive
        raise InputError(f"{path}: not a readable .npz archive ({type(e).__name__}: {e}); expected psi, tau, fps") \
            from None
    for key in ("psi", "tau", "fps"):
        if key not in data:
            raise InputError(f"{path}: no '{key}' array (found: {', '.join(sorted(data)) or 'none'}); "
                             f"expected psi [T,55], tau [T], fps")
    psi, tau = np.asarray(data["psi"]), np.asarray(data["tau"])
    if psi.ndim != 2 or psi.shape[1] != NUM_EXPRESSIONS or not np.issubdtype(psi.dtype, np.number):
        raise InputError(f"{path}: 'psi' has shape {psi.shape} ({psi.dtype}), expected expression weights [T,55]")
    if tau.ndim == 2 and tau.shape[1] == 1:
        tau = tau[:, 0]
    if tau.ndim != 1 or not np.issubdtype(tau.dtype, np.number):
        raise InputError(f"{path}: 'tau' has shape {tau.shape} ({tau.dtype}), expected a larynx slide [T]")
    if len(tau) != len(psi):
        raise InputError(f"{path}: 'psi' has {len(psi)} frames but 'tau' has {len(tau)}; expected equal lengths")
    if len(psi) < 2:
        raise InputError(f"{path}: {len(psi)} frame(s), expected at least 2")
    for key, array in (("psi", psi), ("tau", tau)):
        bad = ~np.isfinite(array)
        if bad.any():
            raise InputError(f"{path}: '{key}' is not finite at frame {int(np.argwhere(bad)[0][0])}")
    check_weights(psi, path, EXPRESSION_NAMES)
    fps = _scalar(data, "fps", path)
    if fps <= 0:
        raise InputError(f"{path}: 'fps' is {fps:g}, expected a positive frame rate")
    subject = _name(data, "subject", path) if "subject" in data else None
    take = (_name(data, "take", path) if "take" in data else None) or take_from_name(path.stem)
    eta = _scalar(data, "eta", path) if "eta" in data else None
    return LarynxSequence(psi.astype(np.float32), tau.astype(np.float32), fps, subject, path.stem, eta, take)


def save_pair(path: str | os.PathLike, sequence: LarynxSequence, time: np.ndarray | None = None) -> None:
    """Write a pair file atomically."""
    arrays = {"psi": sequence.psi.astype(np.float32), "tau": sequence.tau.astype(np.float32),
              "fps": np.float64(sequence.fps)}
    if sequence.subject is not None:
        arrays["subject"] = np.str_(sequence.subject)
    if sequence.eta is not None:
        arrays["eta"] = np.float64(sequence.eta)
    if sequence.take is not None:
        arrays["take"] = np.str_(sequence.take)
    if time is not None:
        arrays["time"] = np.asarray(time, dtype=np.float64)
    save_npz(path, **arrays)


def load_pairs(folder: str | os.PathLike, fps: float | None = None) -> list[LarynxSequence]:
    """Every ``*.npz`` pair file in ``folder`` (sorted by name), resampled to ``fps`` if given."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder; expected a folder of pair files (.npz with psi, tau, fps)")
    files = sorted(folder.glob("*.npz"))
    if not files:
        raise InputError(f"{folder}: no .npz pair files; make them with python -m data.pairs")
    pairs = [load_pair(f) for f in files]
    return pairs if fps is None else [p.resampled(fps) for p in pairs]


def split_by_take(pairs: list[LarynxSequence], val_fraction: float, seed: int,
                  what: str = "take") -> tuple[list[LarynxSequence], list[LarynxSequence]]:
    """(training, validation) pairs, no take on both sides: ``data.splits.split_by_file`` over the takes
    (``round(val_fraction * takes)`` held out, drawn from ``seed``), each list in the input order.

    With a single take (every file of one recording) the split falls back to files, and says so.
    """
    takes = sorted({p.take for p in pairs})
    if len(takes) < 2:
        if len(pairs) >= 2:
            print(f"data.pairs: all {len(pairs)} pair files are one take ('{takes[0]}'): validation by file")
        return split_by_file(pairs, val_fraction, seed, what.replace("take", "pair file"))
    _, held = split_by_file(takes, val_fraction, seed, what)
    held = set(held)
    return [p for p in pairs if p.take not in held], [p for p in pairs if p.take in held]


# --------------------------------------------------------------------------- alignment


def align_pair(track: TauTrack, expressions: ExpressionTrack, fps: float | None = None, offset: float = 0.0,
               subject: str | None = None, name: str = "") -> tuple[LarynxSequence, np.ndarray]:
    """Align a tau track with an expression recording by time, resampled to ``fps`` on their overlap.

    ``offset`` (s) is added to the track's time.  ``fps`` defaults to the expression rate.
    Returns (the pair, its time [T] in seconds on the expression clock).
    """
    fps = float(expressions.fps if fps is None else fps)
    if not fps > 0:
        raise InputError(f"fps must be positive, got {fps}")
    track_time = track.time + offset
    start = max(track_time[0], expressions.time[0])
    stop = min(track_time[-1], expressions.time[-1])
    if stop - start < 1.0 / fps:
        raise InputError(
            f"{track.source} covers {track_time[0]:.3f}-{track_time[-1]:.3f} s (offset {offset:+g} s) and "
            f"{expressions.source} covers {expressions.time[0]:.3f}-{expressions.time[-1]:.3f} s: they overlap "
            f"by less than one frame at {fps:g} fps; check the files or give offset=<seconds>"
        )
    time, psi = resample_uniform(expressions.time, expressions.psi, fps, start, stop)
    _, tau = resample_uniform(track_time, track.tau, fps, start, stop)
    pair = LarynxSequence(psi.astype(np.float32), tau.astype(np.float32), fps, subject, name)
    return pair, time


def run(cfg: DictConfig) -> LarynxSequence:
    """``python -m data.pairs``: align, write and report."""
    track = read_tau_track(cfg.track, fps=cfg.track_fps, min_confidence=cfg.min_confidence, fps_key="track_fps")
    expressions = read_expressions(cfg.expressions, fps=cfg.expressions_fps, timecode_fps=cfg.timecode_fps,
                                   fps_key="expressions_fps")
    pair, time = align_pair(track, expressions, cfg.fps, float(cfg.offset),
                            None if cfg.subject is None else str(cfg.subject), Path(cfg.out).stem)
    save_pair(cfg.out, pair, time)
    print(f"{cfg.out}: {len(pair)} frames at {pair.fps:g} fps ({time[0]:.3f}-{time[-1]:.3f} s of {cfg.expressions})")
    return pair
