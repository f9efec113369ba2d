"""motion.live.packet: a hand-built v6 datagram (struct, not the encoder), the round trip, and each refusal."""
from __future__ import annotations

import struct

import numpy as np
import pytest

from data.expressions import EXPRESSION_NAMES
from motion.live.packet import EAR_BLENDSHAPES, VALUE_COUNT, PacketError, encode, parse

# Positions typed from Unreal's EARFaceBlendShape enum (the list), not taken from the module.
KNOWN = {"EyeBlinkLeft": 0, "EyeBlinkRight": 7, "JawOpen": 17, "MouthClose": 18, "MouthSmileLeft": 23,
         "MouthSmileRight": 24, "BrowInnerUp": 43, "CheekPuff": 46, "NoseSneerRight": 50, "TongueOut": 51}


def datagram(device=b"6C3A2E5F-0000-4000-8000-000000000001", subject=b"Ana", frame=2_160_000, subframe=0.25,
             rate=(60, 1), count=61, values=None, version=6) -> bytes:
    values = np.zeros(61, dtype=np.float64) if values is None else values
    return (struct.pack(">B", version) + struct.pack(">i", len(device)) + device + struct.pack(">i", len(subject))
            + subject + struct.pack(">ifii", frame, subframe, *rate) + struct.pack(">B", count)
            + struct.pack(">61f", *values))


def known_values() -> np.ndarray:
    values = np.zeros(61)
    for k, position in enumerate(KNOWN.values()):
        values[position] = 0.05 * (k + 1)
    values[52:55] = (0.3, -0.2, 0.1)  # HeadYaw, HeadPitch, HeadRoll
    values[55:61] = (0.01, 0.02, 0.03, 0.04, 0.05, 0.06)
    return values


def test_known_datagram_in_unreal_order():
    values = known_values()
    data = datagram(values=values)
    assert len(data) == 26 + 36 + 3 + 4 * 61  # the layout: 26 + L + N + 61 f32
    frame = parse(data)
    assert (frame.device, frame.subject, frame.frame, frame.subframe, frame.rate) == (
        "6C3A2E5F-0000-4000-8000-000000000001", "Ana", 2_160_000, 0.25, (60, 1))
    for name, position in KNOWN.items():
        assert EAR_BLENDSHAPES[position] == name
    np.testing.assert_allclose(frame.head_ypr, [0.3, -0.2, 0.1], rtol=1e-6)
    psi = frame.psi()
    hack = dict(zip(EXPRESSION_NAMES, psi))
    expected = {"eyeBlink_L": "EyeBlinkLeft", "eyeBlink_R": "EyeBlinkRight", "jawOpen": "JawOpen",
                "mouthClose": "MouthClose", "mouthSmile_L": "MouthSmileLeft", "mouthSmile_R": "MouthSmileRight",
                "browInnerUp_L": "BrowInnerUp", "browInnerUp_R": "BrowInnerUp", "cheekPuff_L": "CheekPuff",
                "cheekPuff_R": "CheekPuff", "noseSneer_R": "NoseSneerRight"}
    for hack_name, ear in expected.items():
        assert hack[hack_name] == pytest.approx(values[KNOWN[ear]], rel=1e-6), hack_name
    assert hack["cheekRaiser_L"] == hack["cheekRaiser_R"] == 0.0  # no ARKit shape
    assert psi.sum() == pytest.approx(sum(values[KNOWN[e]] for e in expected.values()), rel=1e-5)  # TongueOut dropped


def test_round_trip():
    rng = np.random.default_rng(0)
    values = rng.uniform(0, 1, VALUE_COUNT).astype(np.float32)
    data = encode("dévice-ü", "Zoë", 123456, values, 0.5, (30, 1))
    assert data == datagram("dévice-ü".encode(), "Zoë".encode(), 123456, 0.5, (30, 1), values=values)
    frame = parse(data)
    assert (frame.device, frame.subject, frame.frame, frame.subframe, frame.rate) == ("dévice-ü", "Zoë", 123456,
                                                                                       0.5, (30, 1))
    np.testing.assert_array_equal(frame.values, values)


def malformed() -> dict[str, tuple[bytes, int]]:
    """Each kind of bad datagram: (bytes, the byte offset the error names)."""
    good = datagram()
    values_at = 26 + 36 + 3
    nan, inf, wild = known_values(), known_values(), known_values()
    nan[17], inf[54], wild[23] = np.nan, np.inf, -9.8e5
    return {
        "empty": (b"", 0),
        "truncated": (good[:-7], values_at),
        "header_only": (good[:20], 5),
        "version": (datagram(version=5), 0),
        "metahuman": (bytes([1]) + good[1:], 0),
        "count": (datagram(count=60), values_at - 1),
        "trailing": (good + b"\0\0\0\0", values_at),
        "negative_length": (bytes([6]) + struct.pack(">i", -1) + good[5:], 1),
        "encoding": (datagram(subject=b"\xff\xfeAna"), 45),
        "rate": (datagram(rate=(0, 1)), 48 + 8),
        "rate_half": (datagram(rate=(1, 2)), 48 + 8),           # 0.5 fps: a ZeroDivisionError before issue 59
        "rate_huge": (datagram(rate=(2**31 - 1, 1)), 48 + 8),   # 16 GiB asked of numpy at the end before
        "rate_negative": (datagram(rate=(-60, -1)), 48 + 8),
        "rate_241": (datagram(rate=(241, 1)), 48 + 8),
        "subframe_nan": (datagram(subframe=float("nan")), 48 + 4),
        "subframe_huge": (datagram(subframe=1e30), 48 + 4),    # an endless loop before issue 59
        "subframe_negative": (datagram(subframe=-1.0), 48 + 4),
        "subframe_one": (datagram(subframe=1.0), 48 + 4),
        "frame_negative": (datagram(frame=-1), 48),
        "frame_max": (datagram(frame=2**31 - 1), 48),
        "frame_next_day": (datagram(frame=86400 * 60), 48),
        "non_finite_nan": (datagram(values=nan), values_at + 4 * 17),
        "non_finite_inf": (datagram(values=inf), values_at + 4 * 54),
        "absurd": (datagram(values=wild), values_at + 4 * 23),
        "no_face": (datagram()[:values_at - 1] + bytes([0]), values_at - 1),
    }


REASON = {"empty": "too_short", "truncated": "too_short", "header_only": "too_short", "version": "version",
          "metahuman": "version", "count": "count", "trailing": "length", "negative_length": "length",
          "encoding": "encoding", "rate": "rate",
          "rate_half": "rate", "rate_huge": "rate", "rate_negative": "rate", "rate_241": "rate",
          "subframe_nan": "subframe", "subframe_huge": "subframe", "subframe_negative": "subframe",
          "subframe_one": "subframe", "frame_negative": "frame", "frame_max": "frame", "frame_next_day": "frame",
          "non_finite_nan": "non_finite", "non_finite_inf": "non_finite",
          "absurd": "absurd", "no_face": "no_face"}


@pytest.mark.parametrize("kind", sorted(REASON))
def test_malformed_reason_and_offset(kind):
    data, offset = malformed()[kind]
    with pytest.raises(PacketError) as caught:
        parse(data)
    assert caught.value.reason == REASON[kind]
    assert caught.value.offset == offset, str(caught.value)
    assert f"at byte {offset}" in str(caught.value) and "expected" in str(caught.value)


@pytest.mark.parametrize("rate, frame, subframe", [((30000, 1001), 86400 * 30 - 1, 0.999), ((1, 1), 0, 0.0),
                                                   ((240, 1), 123, 0.5), ((24, 1), 86400 * 24 - 1, 0.0)])
def test_range_edges_accepted(rate, frame, subframe):
    """The edges of each range are legal: 1 and 240 fps, NTSC's 30000/1001, the day's last frame."""
    parsed = parse(datagram(rate=rate, frame=frame, subframe=subframe))
    assert (parsed.rate, parsed.frame) == (rate, frame) and parsed.subframe == pytest.approx(subframe, abs=1e-6)
