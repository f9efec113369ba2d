"""Pair files: :class:`LarynxSequence` (expression weights and tau at one rate) saved and loaded as ``.npz``,
folders of them, and their split into training and validation by take.

A folder may also hold fit (or ``infer.py``) output folders, each with its ``params.npz``
(``data.params``): each is one take named after its folder, psi reordered by expression name, tau as
fitted, eta the mean of its ``eta [T]`` (a fit writes one value per sequence, repeated), f0 when present.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError
from base.files import save_npz
from base.timebase import resample_uniform
from data.expressions import EXPRESSION_NAMES, NUM_EXPRESSIONS, check_weights
from data.params import ARRAY_KEYS, load_params
from data.splits import split_by_file


@dataclass
class LarynxSequence:
    """One recording: psi [T,55] float32, tau [T] float32 (UV units), both at ``fps``.

    ``subject`` names the person (None if unknown); ``eta`` is the larynx size if known; ``take`` names
    the recording the sequence was cut from (None: the sequence is a recording of its own, ``name``);
    ``f0`` [T] float32 is the voice's fundamental frequency in Hz (0 = unvoiced), None if not recorded.
    """

    psi: np.ndarray
    tau: np.ndarray
    fps: float
    subject: str | None
    name: str
    eta: float | None = None
    take: str | None = None
    f0: np.ndarray | None = None

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
        f0 = None
        if self.f0 is not None:  # nearest frame: a blend of voiced and unvoiced (0) frames is no F0
            nearest = np.clip(np.rint(np.arange(len(tau)) / fps * self.fps).astype(int), 0, len(self) - 1)
            f0 = self.f0[nearest]
        return LarynxSequence(psi.astype(np.float32), tau.astype(np.float32), float(fps), self.subject, self.name,
                              self.eta, self.take, f0)


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


def load_fitted_pair(path: str | os.PathLike, take: str | None = None) -> LarynxSequence:
    """A ``params.npz`` (``data.params``; a ``motion.fit`` or ``infer.py`` output) as one take, named ``take``
    (default: its folder's name for ``params.npz``, else :func:`take_from_name` of the file's stem)."""
    path = Path(path)
    params = load_params(path)
    missing = [n for n in EXPRESSION_NAMES if n not in params.expression_names]
    if missing:
        raise InputError(f"{path}: psi lacks the expressions {missing[:3]}{' ...' if len(missing) > 3 else ''}; "
                         f"expected HACK's {NUM_EXPRESSIONS}")
    if len(params) < 2:
        raise InputError(f"{path}: {len(params)} frame(s), expected at least 2")
    psi = params.psi[:, [params.expression_names.index(n) for n in EXPRESSION_NAMES]]
    check_weights(psi, path, EXPRESSION_NAMES)
    if take is None:
        take = path.parent.resolve().name if path.name == "params.npz" else take_from_name(path.stem)
    return LarynxSequence(psi.astype(np.float32), params.tau.astype(np.float32), float(params.fps), None, take,
                          float(np.mean(params.eta)), take, params.f0)


def load_pair(path: str | os.PathLike) -> LarynxSequence:
    """Read and validate a pair file (its take: the ``take`` entry, else :func:`take_from_name`); a params
    file (``data.params``) goes to :func:`load_fitted_pair`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: file not found")
    try:
        data = dict(np.load(path, allow_pickle=False))
    except Exception as e:  # numpy raises several types for a damaged archive
        raise InputError(f"{path}: not a readable .npz archive ({type(e).__name__}: {e}); expected psi, tau, fps") \
            from None
    if all(key in data for key in ARRAY_KEYS):
        return load_fitted_pair(path)
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
    f0 = None
    if "f0" in data:
        f0 = np.asarray(data["f0"])
        if f0.shape != tau.shape or not np.issubdtype(f0.dtype, np.number):
            raise InputError(f"{path}: 'f0' has shape {f0.shape} ({f0.dtype}), expected F0 in Hz per frame "
                             f"[{len(tau)}]")
        bad = ~np.isfinite(f0) | (f0 < 0)
        if bad.any():
            raise InputError(f"{path}: 'f0' is {f0[bad][0]} at frame {int(np.argmax(bad))}; expected Hz >= 0 "
                             f"(0 = unvoiced)")
        f0 = f0.astype(np.float32)
    return LarynxSequence(psi.astype(np.float32), tau.astype(np.float32), fps, subject, path.stem, eta, take, f0)


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
    if sequence.f0 is not None:
        arrays["f0"] = np.asarray(sequence.f0, dtype=np.float32)
    if time is not None:
        arrays["time"] = np.asarray(time, dtype=np.float64)
    save_npz(path, **arrays)


def load_pairs(folder: str | os.PathLike, fps: float | None = None) -> list[LarynxSequence]:
    """Every ``*.npz`` pair file in ``folder`` and every ``<sub folder>/params.npz`` (a fit's output folder,
    one take named after the sub folder), sorted by name, resampled to ``fps`` if given."""
    folder = Path(folder)
    if not folder.is_dir():
        raise InputError(f"{folder}: not a folder; expected a folder of pair files (.npz with psi, tau, fps) or of "
                         "fit folders (each with its params.npz)")
    files = sorted([*folder.glob("*.npz"), *folder.glob("*/params.npz")])
    if not files:
        raise InputError(f"{folder}: no .npz pair files and no fit folders (<name>/params.npz); make pair files "
                         "with python -m data.pairs, fits with python -m motion.fit")
    pairs = [load_pair(f) for f in files]
    return pairs if fps is None else [p.resampled(fps) for p in pairs]


def split_by_take(pairs: list[LarynxSequence], val_fraction: float, seed: int, what: str = "take", fold: int = 0,
                  folds: int = 1) -> tuple[list[LarynxSequence], list[LarynxSequence]]:
    """(training, validation) pairs, no take on both sides: ``data.splits.split_by_file`` over the takes
    (``round(val_fraction * takes)`` held out, drawn from ``seed``; validation fold ``fold`` of ``folds``),
    each list in the input order.

    With a single take (every file of one recording) the split falls back to files, and says so.
    """
    takes = sorted({p.take for p in pairs})
    if len(takes) < 2:
        if len(pairs) >= 2:
            print(f"data.pairs: all {len(pairs)} pair files are one take ('{takes[0]}'): validation by file")
        return split_by_file(pairs, val_fraction, seed, what.replace("take", "pair file"), fold, folds)
    _, held = split_by_file(takes, val_fraction, seed, what, fold, folds)
    held = set(held)
    return [p for p in pairs if p.take not in held], [p for p in pairs if p.take in held]
