"""Expression recordings: the 55 HACK expression names and the readers for capture files.

The HACK expression space is ICT-FaceKit's 55 blendshapes (all ICT shapes but
``PupilDilate_L/R``) in sorted name order.  Names follow ARKit with ``_L/_R``
for the subject's left and right.  Mapping from ARKit's 52 names:
``browInnerUp`` and ``cheekPuff`` drive both sides, ``cheekRaiser_L/R`` has
no ARKit counterpart (left at 0), ARKit's ``tongueOut`` has no shape (dropped).

Readable formats (:func:`read_expressions`):
- Live Link Face CSV (``Timecode,BlendShapeCount,EyeBlinkLeft,...,HeadYaw,
  HeadPitch,HeadRoll,...``), timecode ``HH:MM:SS:FF.fff`` where ``FF.fff`` is a
  frame (with its fraction) at the timecode rate;
- an ARKit CSV: columns named by ARKit (any case, optional ``blendShapes.``
  prefix) with a ``time``/``timestamp`` (seconds) or ``frame`` column;
- a HACK CSV: columns named by the 55 HACK names, same time columns;
- a header-less CSV of 55 numbers per row, or a ``.npy`` array ``[T,55]``, in
  HACK order (these need ``fps``).

A rate the reader needs and cannot find is asked for by the caller's config
key: ``read_expressions(..., fps_key="expressions_fps")`` makes the error say
``give expressions_fps=...`` (default ``fps``); the timecode rate is
``timecode_fps``.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from base.errors import InputError, require_file
from base.files import load_npy
from base.rotations import matrix_to_quaternion, quaternion_to_matrix
from base.tables import CsvTable
from base.timebase import resample_held, resample_uniform, row_name, time_axis

EXPRESSION_NAMES: tuple[str, ...] = (
    "browDown_L", "browDown_R", "browInnerUp_L", "browInnerUp_R", "browOuterUp_L", "browOuterUp_R",
    "cheekPuff_L", "cheekPuff_R", "cheekRaiser_L", "cheekRaiser_R", "cheekSquint_L", "cheekSquint_R",
    "eyeBlink_L", "eyeBlink_R", "eyeLookDown_L", "eyeLookDown_R", "eyeLookIn_L", "eyeLookIn_R",
    "eyeLookOut_L", "eyeLookOut_R", "eyeLookUp_L", "eyeLookUp_R", "eyeSquint_L", "eyeSquint_R",
    "eyeWide_L", "eyeWide_R", "jawForward", "jawLeft", "jawOpen", "jawRight", "mouthClose",
    "mouthDimple_L", "mouthDimple_R", "mouthFrown_L", "mouthFrown_R", "mouthFunnel", "mouthLeft",
    "mouthLowerDown_L", "mouthLowerDown_R", "mouthPress_L", "mouthPress_R", "mouthPucker", "mouthRight",
    "mouthRollLower", "mouthRollUpper", "mouthShrugLower", "mouthShrugUpper", "mouthSmile_L",
    "mouthSmile_R", "mouthStretch_L", "mouthStretch_R", "mouthUpperUp_L", "mouthUpperUp_R",
    "noseSneer_L", "noseSneer_R",
)
NUM_EXPRESSIONS = len(EXPRESSION_NAMES)
assert NUM_EXPRESSIONS == 55


def arkit_name(hack_name: str) -> str | None:
    """The ARKit blendshape that drives a HACK expression, or None if ARKit has none."""
    base, _, side = hack_name.rpartition("_")
    if side not in ("L", "R"):
        return hack_name
    if base in ("browInnerUp", "cheekPuff"):
        return base
    if base == "cheekRaiser":
        return None
    return base + ("Left" if side == "L" else "Right")


# Range a blendshape weight may take before we call the file malformed: trackers
# overshoot [0, 1] slightly, degrees or percent do not fit.
WEIGHT_RANGE = (-0.1, 1.5)
HEAD_COLUMNS = ("HeadYaw", "HeadPitch", "HeadRoll")
_PREFIX = re.compile(r"^(blendshapes?[._:])", re.IGNORECASE)


@dataclass
class ExpressionTrack:
    """An expression recording in the HACK space.

    psi:      [T,55] float32 expression weights in ``EXPRESSION_NAMES`` order.
    time:     [T] seconds, increasing.
    fps:      frame rate (frames per second) of the recording.
    head_ypr: [T,3] head yaw, pitch, roll in radians as recorded (Live Link
              Face ``HeadYaw, HeadPitch, HeadRoll``), or None.
    missing:  HACK names the file did not provide (left at 0).
    source:   the file it was read from.
    head_rotation: [T,3,3] head orientations in the rig's world frame (``motion.head2neck``'s ``matrix``
              input: y up, face towards +z, x to the subject's left), or None; a face tracker's pose
              (``motion.face``) comes this way rather than as angles.
    tracked:  [T] bool, the frames where a face tracker found the face (the others are filled in), or
              None for a capture file.
    """

    psi: np.ndarray
    time: np.ndarray
    fps: float
    head_ypr: np.ndarray | None = None
    missing: list[str] = field(default_factory=list)
    source: str = ""
    head_rotation: np.ndarray | None = None
    tracked: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.psi)

    def resampled(self, fps: float, gap: float | None = None) -> ExpressionTrack:
        """The same recording linearly resampled to a uniform grid at ``fps`` (rotations by normalised
        quaternion interpolation; ``tracked`` belongs to the recorded frames and is not carried over).
        ``gap`` (s): under the gap rule (``base.timebase.resample_held``: frames further apart than ``gap``
        are not interpolated over, the points between them hold the last one before)."""
        def resample(values):
            if gap is None:
                return resample_uniform(self.time, values, fps)
            return resample_held(self.time, values, fps, gap)

        time, psi = resample(self.psi)
        head = None if self.head_ypr is None else resample(self.head_ypr)[1]
        rotation = None if self.head_rotation is None else resample_rotations(self.time, self.head_rotation, fps,
                                                                               gap)
        return ExpressionTrack(psi.astype(np.float32), time, float(fps), head, list(self.missing), self.source,
                               rotation)

    def mirrored(self) -> ExpressionTrack:
        """The recording of a mirrored image (selfie footage) as the subject moved: left and right weights
        swapped, yaw and roll negated (``head_ypr``), and rotations reflected through the mid-sagittal
        plane, ``S R S`` with ``S = diag(-1, 1, 1)``, which negates yaw and roll and keeps pitch."""
        psi = self.psi[:, [EXPRESSION_NAMES.index(mirror_name(name)) for name in EXPRESSION_NAMES]]
        head = None if self.head_ypr is None else self.head_ypr * np.array([-1.0, 1.0, -1.0], dtype=self.head_ypr.dtype)
        rotation = None
        if self.head_rotation is not None:
            flip = np.diag([-1.0, 1.0, 1.0]).astype(self.head_rotation.dtype)
            rotation = flip @ self.head_rotation @ flip
        missing = sorted({mirror_name(name) for name in self.missing}, key=EXPRESSION_NAMES.index)
        return ExpressionTrack(psi, self.time, self.fps, head, missing, self.source, rotation, self.tracked)


def mirror_name(hack_name: str) -> str:
    """The HACK expression of the other side (``eyeBlink_L`` <-> ``eyeBlink_R``, ``jawLeft`` <-> ``jawRight``,
    ``mouthLeft`` <-> ``mouthRight``); a name without a side is its own mirror."""
    swaps = {"_L": "_R", "_R": "_L", "Left": "Right", "Right": "Left"}
    for ending, other in swaps.items():
        if hack_name.endswith(ending):
            return hack_name[: -len(ending)] + other
    return hack_name


def resample_rotations(time: np.ndarray, rotations: np.ndarray, fps: float, gap: float | None = None) -> np.ndarray:
    """Rotations [T,3,3] at ``time`` resampled on :func:`resample_uniform`'s grid at ``fps``: quaternions
    made continuous (each on the side of the previous one), interpolated linearly and normalised."""
    quaternions = matrix_to_quaternion(torch.as_tensor(np.asarray(rotations, dtype=np.float64))).numpy()
    signs = np.sign(np.einsum("ti,ti->t", quaternions[1:], quaternions[:-1]))
    quaternions[1:] *= np.cumprod(np.where(signs == 0, 1.0, signs))[:, None]
    if gap is None:
        _, resampled = resample_uniform(time, quaternions, fps)
    else:
        _, resampled = resample_held(time, quaternions, fps, gap)
    resampled /= np.linalg.norm(resampled, axis=1, keepdims=True)
    matrices = quaternion_to_matrix(torch.as_tensor(resampled)).numpy()
    return matrices.astype(np.asarray(rotations).dtype)


def check_weights(psi: np.ndarray, path: Path, names, lines: list[int] | None = None) -> None:
    lo, hi = WEIGHT_RANGE
    bad = (psi < lo) | (psi > hi)
    if bad.any():
        row, col = np.argwhere(bad)[0]
        raise InputError(
            f"{path}: column '{names[col]}', {row_name(lines, row)}: weight {psi[row, col]:g} outside "
            f"[{lo}, {hi}]; expected blendshape weights in [0, 1]"
        )


def _read_headerless(path: Path, fps: float | None, fps_key: str) -> ExpressionTrack:
    table = CsvTable(path, columns=EXPRESSION_NAMES)  # numbers, finite, 55 per line: errors name line and column
    if fps is None:
        raise InputError(f"{path}: a header-less table carries no frame rate; give {fps_key}=...")
    psi = np.stack([table.numeric(name) for name in EXPRESSION_NAMES], axis=1)
    check_weights(psi, path, EXPRESSION_NAMES, table.lines)
    return ExpressionTrack(psi.astype(np.float32), np.arange(len(psi)) / fps, float(fps), source=str(path))


def read_expressions(path: str | os.PathLike, fps: float | None = None,
                     timecode_fps: float | None = None, fps_key: str = "fps") -> ExpressionTrack:
    """Read an expression recording (Live Link Face, ARKit, HACK CSV, or ``.npy``) into the HACK space.

    ``fps``: the rate of a recording without time stamps (header-less CSV, ``.npy``, a ``frame``
    column); ``timecode_fps``: the rate of Live Link Face timecode frames (else guessed from the
    frame numbers); ``fps_key``: the caller's config key for ``fps``, named in errors.
    """
    path = require_file(path)
    if path.suffix.lower() == ".npy":
        psi = load_npy(path, 2, "expression weights [T,55]")
        if psi.shape[1] != NUM_EXPRESSIONS:
            raise InputError(f"{path}: array of shape {psi.shape}, expected expression weights [T,55]")
        if fps is None:
            raise InputError(f"{path}: a .npy expression array carries no frame rate; give {fps_key}=...")
        check_weights(psi, path, EXPRESSION_NAMES)
        return ExpressionTrack(psi.astype(np.float32), np.arange(len(psi)) / fps, float(fps), source=str(path))
    if path.suffix.lower() != ".csv":
        raise InputError(f"{path}: unsupported expression format '{path.suffix}', expected .csv or .npy")

    try:
        with open(path, encoding="utf-8-sig") as f:
            first = f.readline().strip().split(",")
    except UnicodeDecodeError as e:
        raise InputError(f"{path}: not a text CSV (byte {e.start} is not UTF-8 text); expected an expression "
                         f"recording") from None
    try:
        [float(x) for x in first]
        headerless = True
    except ValueError:
        headerless = False
    if headerless:  # outside the try: InputError is a ValueError and must reach the caller
        if len(first) != NUM_EXPRESSIONS:
            raise InputError(f"{path}: {len(first)} columns without a header, expected 55 in HACK order")
        return _read_headerless(path, fps, fps_key)

    # Live Link Face writes "<timecode>,0" under its wide header when tracking is lost: those frames are
    # dropped (resampling to a uniform grid interpolates over them).  A two-column file keeps its rows.
    header_width = len(first)
    table = CsvTable(path, skip_row=lambda row: header_width > 2 and len(row) == 2 and row[1].strip() == "0")
    lower = {_PREFIX.sub("", h).lower(): h for h in table.header}
    psi = np.zeros((len(table), NUM_EXPRESSIONS), dtype=np.float64)
    used, missing = [], []
    columns = list(EXPRESSION_NAMES)
    for k, name in enumerate(EXPRESSION_NAMES):
        candidates = [name, arkit_name(name)]
        column = next((lower[c.lower()] for c in candidates if c and c.lower() in lower), None)
        if column is None:
            missing.append(name)
            continue
        psi[:, k] = table.numeric(column)
        columns[k] = column
        used.append(column)
    if not used:
        raise InputError(
            f"{path}: no expression columns found; expected ARKit names (e.g. EyeBlinkLeft, JawOpen) "
            f"or HACK names (e.g. eyeBlink_L, jawOpen). Columns: {', '.join(table.header[:12])}"
            + (" ..." if len(table.header) > 12 else "")
        )
    check_weights(psi, path, columns, table.lines)
    time, rate = time_axis(table, fps, timecode_fps, fps_key)
    head = None
    if all(table.has(c) for c in HEAD_COLUMNS):
        head = np.stack([table.numeric(c) for c in HEAD_COLUMNS], axis=1)
        if not head.any():  # Live Link Face writes zeros when head rotation was not recorded
            head = None
    return ExpressionTrack(psi.astype(np.float32), time, rate, head, missing, str(path))
