"""One Live Link Face "ARKit" datagram (packet version 6): parsed into a :class:`Frame`, or refused with a reason.

Layout (issue 42, after Unreal's ``AppleARKitLiveLinkSource.cpp`` for version 6; all multi-byte fields
big-endian):

    offset      type        field
    0           u8          packet version (6)
    1           i32 L       then L bytes: device id (UTF-8, a UUID)
    5+L         i32 N       then N bytes: subject name (UTF-8)
    9+L+N       i32, f32    frame number, sub-frame
    17+L+N      i32, i32    frame-rate numerator, denominator
    25+L+N      u8          value count (61)
    26+L+N      61 x f32    52 ARKit weights in Unreal's EARFaceBlendShape order, HeadYaw, HeadPitch,
                            HeadRoll, left eye yaw, pitch, roll, right eye yaw, pitch, roll

A datagram with the count byte 0 and nothing after it is the app's "no face" packet (tracking lost).
Any other version (v1-v5 of older apps, the "MetaHuman Animator" protocol with its handshake) is
refused by its version byte; nothing else is guessed.  :func:`encode` is the inverse, for the sender.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np

from data.expressions import EXPRESSION_NAMES, arkit_name

VERSION = 6
VALUE_COUNT = 61
# Unreal's EARFaceBlendShape enum order (AppleARKitFaceSupport / ARTrackable.h): the order of the 52
# weights in the datagram and of the weight columns of a Live Link Face CSV.  Not alphabetical.
EAR_BLENDSHAPES: tuple[str, ...] = (
    "EyeBlinkLeft", "EyeLookDownLeft", "EyeLookInLeft", "EyeLookOutLeft", "EyeLookUpLeft", "EyeSquintLeft",
    "EyeWideLeft", "EyeBlinkRight", "EyeLookDownRight", "EyeLookInRight", "EyeLookOutRight", "EyeLookUpRight",
    "EyeSquintRight", "EyeWideRight", "JawForward", "JawLeft", "JawRight", "JawOpen", "MouthClose",
    "MouthFunnel", "MouthPucker", "MouthLeft", "MouthRight", "MouthSmileLeft", "MouthSmileRight",
    "MouthFrownLeft", "MouthFrownRight", "MouthDimpleLeft", "MouthDimpleRight", "MouthStretchLeft",
    "MouthStretchRight", "MouthRollLower", "MouthRollUpper", "MouthShrugLower", "MouthShrugUpper",
    "MouthPressLeft", "MouthPressRight", "MouthLowerDownLeft", "MouthLowerDownRight", "MouthUpperUpLeft",
    "MouthUpperUpRight", "BrowDownLeft", "BrowDownRight", "BrowInnerUp", "BrowOuterUpLeft", "BrowOuterUpRight",
    "CheekPuff", "CheekSquintLeft", "CheekSquintRight", "NoseSneerLeft", "NoseSneerRight", "TongueOut",
)
NUM_WEIGHTS = len(EAR_BLENDSHAPES)
assert NUM_WEIGHTS == 52
HEAD_NAMES = ("HeadYaw", "HeadPitch", "HeadRoll")
EYE_NAMES = ("LeftEyeYaw", "LeftEyePitch", "LeftEyeRoll", "RightEyeYaw", "RightEyePitch", "RightEyeRoll")
VALUE_NAMES = EAR_BLENDSHAPES + HEAD_NAMES + EYE_NAMES  # the 61 values; also the Live Link Face CSV columns
assert len(VALUE_NAMES) == VALUE_COUNT

# psi [55] from the 52 weights through data.expressions' own mapping (arkit_name: the ARKit blendshape that
# drives a HACK expression, matched case-blind as read_expressions matches CSV columns); -1: no ARKit shape.
_EAR_INDEX = {name.lower(): k for k, name in enumerate(EAR_BLENDSHAPES)}
HACK_FROM_EAR = np.array([_EAR_INDEX[arkit_name(n).lower()] if arkit_name(n) else -1 for n in EXPRESSION_NAMES])
_DRIVEN = HACK_FROM_EAR >= 0

MAX_NAME_BYTES = 256  # device ids are UUIDs (36 bytes), subjects short names: longer is garbage
_TIMING = struct.Struct(">ifii")  # frame, sub-frame, rate numerator, denominator
_VALUES = struct.Struct(f">{VALUE_COUNT}f")
MIN_FPS, MAX_FPS = 1, 240   # the frame rates a datagram may carry (Live Link Face sends 60, 30, 24, ...)
SECONDS_PER_DAY = 86400    # frame numbers count the timecode of the day
REASONS = ("too_short", "version", "length", "encoding", "rate", "subframe", "frame", "count", "non_finite",
           "absurd", "no_face")


class PacketError(ValueError):
    """A datagram that is not a usable v6 frame: ``reason`` (one of :data:`REASONS` or ``no_face``), the byte
    ``offset`` where it fails, and what was expected (the message)."""

    def __init__(self, reason: str, offset: int, message: str):
        super().__init__(f"{reason} at byte {offset}: {message}")
        self.reason, self.offset = reason, offset


@dataclass
class Frame:
    """One parsed datagram: the phone (device id, subject), the frame's timecode and the 61 values."""

    device: str
    subject: str
    frame: int
    subframe: float
    rate: tuple[int, int]
    values: np.ndarray  # [61] float32 in VALUE_NAMES order

    @property
    def fps(self) -> float:
        return self.rate[0] / self.rate[1]

    @property
    def weights(self) -> np.ndarray:
        return self.values[:NUM_WEIGHTS]

    @property
    def head_ypr(self) -> np.ndarray:
        return self.values[NUM_WEIGHTS:NUM_WEIGHTS + 3]

    def psi(self) -> np.ndarray:
        """The 55 HACK expression weights [55] float32 (cheekRaiser_L/R, which ARKit lacks, at 0)."""
        out = np.zeros(len(EXPRESSION_NAMES), dtype=np.float32)
        out[_DRIVEN] = self.weights[HACK_FROM_EAR[_DRIVEN]]
        return out


def _name(data: bytes, offset: int, what: str) -> tuple[str, int]:
    """A length-prefixed UTF-8 string at ``offset``: (text, offset after it)."""
    if len(data) < offset + 4:
        raise PacketError("too_short", offset, f"{len(data)} bytes, expected the i32 length of the {what}")
    (length,) = struct.unpack_from(">i", data, offset)
    if not 0 <= length <= MAX_NAME_BYTES:
        raise PacketError("length", offset, f"{what} length {length}, expected 0..{MAX_NAME_BYTES}")
    start = offset + 4
    if len(data) < start + length:
        raise PacketError("too_short", start, f"{len(data)} bytes, expected {length} bytes of {what}")
    try:
        text = data[start:start + length].decode("utf-8")
    except UnicodeDecodeError as e:
        raise PacketError("encoding", start + e.start, f"{what} byte 0x{data[start + e.start]:02x}, expected "
                                                      f"UTF-8 text") from None
    return text, start + length


def parse(data: bytes, absurd: float = 10.0) -> Frame:
    """The :class:`Frame` of one v6 datagram; :class:`PacketError` naming the reason, offset and expectation.

    Values are checked for finiteness (``non_finite``) and for weights beyond +-``absurd`` (``absurd``:
    e.g. the -9.8e5 seen in the wild); weights merely outside ``data.expressions.WEIGHT_RANGE`` pass
    (the stream clamps and counts them)."""
    if len(data) < 1:
        raise PacketError("too_short", 0, "empty datagram, expected the version byte")
    if data[0] != VERSION:
        raise PacketError("version", 0, f"packet version {data[0]}, expected {VERSION} (Live Link Face 'ARKit' "
                                        f"mode; MetaHuman Animator mode and older versions are not read)")
    device, offset = _name(data, 1, "device id")
    subject, offset = _name(data, offset, "subject name")
    if len(data) < offset + _TIMING.size + 1:
        raise PacketError("too_short", offset, f"{len(data)} bytes, expected {offset + _TIMING.size + 1} "
                                               f"(frame, sub-frame, rate, value count)")
    frame, subframe, numerator, denominator = _TIMING.unpack_from(data, offset)
    # each field checked against its range before anything uses it (issue 59): integers compared exactly
    if not (denominator > 0 and MIN_FPS * denominator <= numerator <= MAX_FPS * denominator):
        raise PacketError("rate", offset + 8, f"rate {numerator}/{denominator}, expected a frame rate of "
                                              f"{MIN_FPS}..{MAX_FPS} fps (60/1, 30000/1001)")
    if not 0.0 <= subframe < 1.0:  # NaN fails too
        raise PacketError("subframe", offset + 4, f"sub-frame {subframe}, expected 0 <= sub-frame < 1")
    day = SECONDS_PER_DAY * int(round(numerator / denominator))
    if not 0 <= frame < day:
        raise PacketError("frame", offset, f"frame {frame}, expected a timecode frame of the day, "
                                           f"0..{day - 1} at {numerator}/{denominator} fps")
    offset += _TIMING.size
    count = data[offset]
    if count == 0 and len(data) == offset + 1:
        raise PacketError("no_face", offset, "value count 0 (the app lost the face), expected 61 values")
    if count != VALUE_COUNT:
        raise PacketError("count", offset, f"value count {count}, expected {VALUE_COUNT}")
    offset += 1
    if len(data) != offset + _VALUES.size:
        reason = "too_short" if len(data) < offset + _VALUES.size else "length"
        raise PacketError(reason, offset, f"{len(data) - offset} bytes of values, expected {_VALUES.size} "
                                          f"({VALUE_COUNT} big-endian f32)")
    values = np.frombuffer(data, dtype=">f4", count=VALUE_COUNT, offset=offset).astype(np.float32)
    finite = np.isfinite(values)
    if not finite.all():
        k = int(np.argmin(finite))
        raise PacketError("non_finite", offset + 4 * k, f"{VALUE_NAMES[k]} = {values[k]}, expected a finite value")
    wild = np.abs(values[:NUM_WEIGHTS]) > absurd
    if wild.any():
        k = int(np.argmax(wild))
        raise PacketError("absurd", offset + 4 * k, f"{VALUE_NAMES[k]} = {values[k]:g}, expected a weight "
                                                    f"within +-{absurd:g}")
    return Frame(device, subject, int(frame), float(subframe), (int(numerator), int(denominator)), values)


def encode(device: str, subject: str, frame: int, values, subframe: float = 0.0,
           rate: tuple[int, int] = (60, 1)) -> bytes:
    """The v6 datagram of one frame (the inverse of :func:`parse`); ``values`` [61] in VALUE_NAMES order."""
    values = np.asarray(values, dtype=np.float32).reshape(-1)
    if len(values) != VALUE_COUNT:
        raise ValueError(f"{len(values)} values, expected {VALUE_COUNT} (VALUE_NAMES)")
    device_bytes, subject_bytes = device.encode("utf-8"), subject.encode("utf-8")
    return b"".join((
        bytes([VERSION]), struct.pack(">i", len(device_bytes)), device_bytes,
        struct.pack(">i", len(subject_bytes)), subject_bytes,
        _TIMING.pack(int(frame), float(subframe), int(rate[0]), int(rate[1])),
        bytes([VALUE_COUNT]), values.astype(">f4").tobytes(),
    ))
