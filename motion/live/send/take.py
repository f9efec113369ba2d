"""A take to replay: rows of (frame number, sub-frame, 61 values) at an integer timecode rate, read from a
Live Link Face CSV or made from the built-in demo take."""
from __future__ import annotations

import re
from dataclasses import dataclass

import numpy as np

from base.errors import InputError
from base.tables import CsvTable
from data.demo_take import demo_take
from data.expressions import EXPRESSION_NAMES, arkit_name
from motion.live.packet import EAR_BLENDSHAPES, NUM_WEIGHTS, VALUE_COUNT, VALUE_NAMES

STANDARD_RATES = (24, 25, 30, 48, 50, 60, 120)  # parse_timecode's guesses, in its order


@dataclass
class Take:
    """frames [T] int, subframes [T], values [T,61] float32 (NaN row: a lost-tracking row), rate (fps)."""

    frames: np.ndarray
    subframes: np.ndarray
    values: np.ndarray
    rate: int


def read_take(path: str, timecode_fps: int | None = None) -> Take:
    """A Live Link Face CSV (``Timecode`` and the 61 value columns; absent ones sent as 0) or ``demo``."""
    if path == "demo":
        return demo_as_take()
    # Live Link Face writes "<timecode>,0" when it lost the face: not sent (a gap the receiver fills)
    table = CsvTable(path, skip_row=lambda row: len(row) == 2 and row[1].strip() == "0")
    if not table.has("Timecode"):
        raise InputError(f"{path}: no 'Timecode' column; expected a Live Link Face CSV")
    parts = []
    for line, code in zip(table.lines, table.text("Timecode")):
        m = re.fullmatch(r"(\d+):(\d+):(\d+)[:;](\d+(?:\.\d+)?)", code.strip())
        if not m:
            raise InputError(f"{path}: column 'Timecode', line {line}: '{code}' is not HH:MM:SS:FF.fff")
        parts.append([float(g) for g in m.groups()])
    hms = np.array(parts).reshape(-1, 4)
    if not len(hms):
        raise InputError(f"{path}: no frames")
    rate = timecode_fps or next((r for r in STANDARD_RATES if r > np.floor(hms[:, 3]).max()), None)
    if rate is None:
        raise InputError(f"{path}: timecode frame {hms[:, 3].max():g} exceeds 120 fps; give timecode_fps=...")
    whole = np.floor(hms[:, 3])
    frames = ((hms[:, 0] * 3600 + hms[:, 1] * 60 + hms[:, 2]) * rate + whole).astype(np.int64)
    values = np.zeros((len(table), VALUE_COUNT), dtype=np.float32)
    for k, name in enumerate(VALUE_NAMES):
        if table.has(name):
            values[:, k] = table.numeric(name)
    return Take(frames, hms[:, 3] - whole, values, int(rate))


def demo_as_take(rate: int = 60) -> Take:
    """The built-in demo take at ``rate`` as ARKit values (each ARKit weight from the HACK expression it
    drives, ``arkit_name``; head yaw, pitch, roll in radians; eyes at 0)."""
    track = demo_take(fps=float(rate))
    values = np.zeros((len(track), VALUE_COUNT), dtype=np.float32)
    index = {name: k for k, name in enumerate(EAR_BLENDSHAPES)}
    for k, name in enumerate(EXPRESSION_NAMES):
        arkit = arkit_name(name)
        if arkit is not None:
            values[:, index[arkit[0].upper() + arkit[1:]]] = track.psi[:, k]
    values[:, NUM_WEIGHTS:NUM_WEIGHTS + 3] = track.head_ypr
    start = 10 * 3600 * rate  # 10:00:00:00, a timecode like the app's (time of day)
    return Take(start + np.arange(len(track)), np.zeros(len(track)), values, rate)
