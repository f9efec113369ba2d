"""motion.live against what the network may send (issue 59), loopback only: a seeded, bounded fuzz of hostile
datagrams interleaved with two phones sending the demo take, and a session killed with SIGKILL."""
from __future__ import annotations

import os
import signal
import socket
import struct
import time
import tracemalloc

import numpy as np

from data.expressions import read_expressions
from data.params import load_params
from motion.live.cli import finish, live_models, stream_options
from motion.live.config import LiveConfig
from motion.live.outputs import SessionWriter
from motion.live.packet import REASONS, encode, parse
from motion.live.receiver import LiveReceiver
from motion.live.send.take import demo_as_take
from motion.pipeline.config import InferConfig
from motion.pipeline.models import load_models
from motion.pipeline.take import run_take
from tests.test_live_receiver import free_port

PHONE_A, PHONE_B = "6C3A2E5F-0000-4000-8000-00000000000a", "6C3A2E5F-0000-4000-8000-00000000000b"
RECEIVER_REASONS = {"late", "jump", "ahead", "address", "too_many_phones", "not_allowed", "stream_error",
                    "socket_error"}
MEMORY_BOUND = 4_000_000  # bytes the receiver may keep after the fuzz (tracemalloc; 0.32 MB measured), recordings in it


def udp_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock


def raw(device: bytes, subject: bytes, frame: int, subframe: float, rate: tuple[int, int], count: int,
        values: np.ndarray) -> bytes:
    """A v6 datagram with any field as given (the encoder's checks bypassed)."""
    return (bytes([6]) + struct.pack(">i", len(device)) + device + struct.pack(">i", len(subject)) + subject
            + struct.pack(">ifii", frame, subframe, *rate) + bytes([count]) + values.astype(">f4").tobytes())


def hostile(rng: np.random.Generator, take, real: list[bytes]) -> tuple[str, bytes]:
    """One hostile datagram: (its kind, bytes).  Every field at its extremes, names with control characters
    and 10 kB, counts 0..255, random bytes, bit flips of the phones' own datagrams, their device ids spoofed."""
    kinds = ("rate", "subframe", "frame", "jump", "count", "name", "random", "flip", "spoof")
    kind = kinds[int(rng.integers(len(kinds)))]
    values = take.values[int(rng.integers(len(take.values)))]
    device = f"evil-{int(rng.integers(5))}".encode()
    frame, subframe, rate, count = int(rng.integers(0, 2000)), 0.0, (60, 1), 61
    if kind == "rate":
        rate = [(0, 1), (-60, 1), (1, 2), (2**31 - 1, 1), (60, 0), (-1, -1), (241, 1), (30000, 1001),
                (1, 1), (240, 1)][int(rng.integers(10))]
    elif kind == "subframe":
        subframe = [float("nan"), 1e30, -1.0, float("inf"), 1.0, 0.9999, 0.5][int(rng.integers(7))]
    elif kind == "frame":
        frame = [0, 2**31 - 1, -1, -2**31, 86400 * 60 - 1, 86400 * 60][int(rng.integers(6))]
    elif kind == "jump":
        frame = int(rng.integers(0, 2**31 - 1))
    elif kind == "count":
        data = raw(device, b"x", frame, 0.0, rate, int(rng.integers(256)), values)
        return kind, data[:int(rng.integers(40, len(data) + 8))]
    elif kind == "name":
        device = [b"\x1b[2J\x1b[31mred\x07", b"A" * 10_000, b"\xff\xfe", "\u202eevil".encode(),
                  b"\n\r\t\x00"][int(rng.integers(5))]
    elif kind == "random":
        return kind, rng.bytes(int(rng.integers(0, 900)))
    elif kind == "flip":
        data = bytearray(real[int(rng.integers(len(real)))])
        for k in rng.integers(0, len(data), int(rng.integers(1, 6))):
            data[k] ^= 1 << int(rng.integers(8))
        return kind, bytes(data)
    elif kind == "spoof":  # a phone's own device id and subject, a later frame, from the attacker's address
        device, which = (PHONE_A.encode(), b"ana") if rng.random() < 0.5 else (PHONE_B.encode(), b"ben")
        return kind, raw(device, which, int(rng.integers(100, 2000)), 0.0, (60, 1), 61, values)
    return kind, raw(device, b"x", frame, subframe, rate, count, values)


def no_face(device: str, subject: str, frame: int) -> bytes:
    """Live Link Face's datagram for a lost face: the header, count 0, nothing after."""
    return encode(device, subject, frame, np.zeros(61))[:-4 * 61 - 1] + bytes([0])


def test_fuzz_two_phones(tmp_path):
    """2 phones (ana: 300 frames; ben: 120 frames, a 4 s face loss sent as no-face datagrams, 120 frames) and
    about 1,500 hostile datagrams, seeded, within 15 s: the receiver never dies, keeps < MEMORY_BOUND, counts every
    refused datagram by reason, and the phones' params equal infer.py on their capture.csv."""
    rng = np.random.default_rng(59)
    take = demo_as_take()
    models = live_models(LiveConfig(), announce=lambda *_: None)
    out = tmp_path / "live"
    out.mkdir()
    printed: list[str] = []
    rx = LiveReceiver(models, stream_options(LiveConfig()), "127.0.0.1", 0, max_phones=4, announce=printed.append,
                      writer=SessionWriter(out, 1.0), idle_seconds=60.0)
    phone_a, phone_b, attacker = udp_socket(), udp_socket(), udp_socket()
    ana = [encode(PHONE_A, "ana", take.frames[i], take.values[i]) for i in range(300)]
    ben = ([encode(PHONE_B, "ben", take.frames[i], take.values[i]) for i in range(120)]
           + [no_face(PHONE_B, "ben", int(take.frames[0]) + i) for i in range(120, 360)]
           + [encode(PHONE_B, "ben", take.frames[i], take.values[i]) for i in range(360, 480)])
    # the two phones interleaved in time, each in its own order, ana's first frame first
    timed = [(k / len(ana), 0, k, phone_a, d) for k, d in enumerate(ana)]
    timed += [(k / len(ben), 1, k, phone_b, d) for k, d in enumerate(ben)]
    real = [(sock, d) for *_, sock, d in sorted(timed, key=lambda item: item[:3])]
    sequence, kinds = real[:2], []  # the phones' first datagrams first: their streams are theirs
    for item in real[2:]:
        sequence.append(item)
        for _ in range(int(rng.integers(0, 5))):
            kind, data = hostile(rng, take, ana + ben)
            kinds.append(kind)
            sequence.append((attacker, data))
    assert len(kinds) > 1500
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    started, handled, deadline = time.monotonic(), 0, time.monotonic() + 15.0
    try:
        for start in range(0, len(sequence), 100):
            batch = sequence[start:start + 100]
            for sock, data in batch:
                sock.sendto(data, rx.address)
            target = start + len(batch)
            while handled < target and time.monotonic() < deadline:
                if rx.wait(0.05):
                    handled += rx.drain()
        grown = sum(s.size_diff for s in tracemalloc.take_snapshot().compare_to(before, "filename"))
    finally:
        tracemalloc.stop()
        for sock in (phone_a, phone_b, attacker):
            sock.close()
    seconds = time.monotonic() - started
    assert handled == len(sequence), f"{handled} of {len(sequence)} datagrams handled in {seconds:.1f} s"
    assert grown < MEMORY_BOUND, f"{grown} bytes kept"
    print(f"fuzz: {len(sequence)} datagrams ({len(kinds)} hostile) in {seconds:.2f} s, {grown} bytes kept")
    assert rx.state_size()["streams"] <= 4 and rx.state_size()["versions"] <= 256
    summary = finish(rx, out, 1.0)
    rx.close()
    # every datagram either accepted into a stream or refused and counted by a known reason
    accepted = sum(entry["frames"] for entry in summary["subjects"].values())
    assert accepted + sum(summary["rejected"].values()) == rx.received == len(sequence)
    assert set(summary["rejected"]) <= set(REASONS) | RECEIVER_REASONS, summary["rejected"]
    assert summary["rejected"]["address"] >= kinds.count("spoof")  # each spoof (and flips of the device-bound)
    assert summary["rejected"]["no_face"] >= 240
    for reason in ("rate", "subframe", "frame", "length", "encoding", "count"):
        assert summary["rejected"].get(reason, 0) > 0, reason
    assert all(line.isprintable() for line in printed), [line for line in printed if not line.isprintable()]
    # the phones lost nothing, and live equals infer.py on their capture.csv (ben through the 4 s gap)
    subjects = summary["subjects"]
    assert subjects["ana"]["frames"] == 300 and subjects["ben"]["frames"] == 240 and subjects["ben"]["gaps"] == 1
    offline_cfg = InferConfig(plot=False)
    offline_models = load_models(offline_cfg, announce=lambda *_: None)
    for name, count in (("ana", 150), ("ben", 240)):
        capture = out / name / "capture.csv"
        run_take(InferConfig(expressions=str(capture), plot=False), offline_models, str(capture),
                 tmp_path / f"offline_{name}", announce=lambda *_: None)
        live, offline = load_params(out / name / "params.npz"), load_params(tmp_path / f"offline_{name}" / "params.npz")
        assert len(live) == len(offline) == count
        np.testing.assert_allclose(live.psi, offline.psi, atol=1e-6)
        np.testing.assert_allclose(live.tau, offline.tau, atol=1e-5)
        np.testing.assert_allclose(live.theta, offline.theta, atol=1e-5)
    ben_tau = load_params(out / "ben" / "params.npz").tau
    assert np.all(ben_tau[60:179] == ben_tau[59])  # the face lost from 2 s to 6 s: held at the frame before


def test_sigkill_keeps_capture(tmp_path):
    """A live session (the command, in a forked process) killed with SIGKILL mid-session: capture.csv holds every
    frame received up to the last flush, and infer.py reproduces them."""
    take = demo_as_take()
    port, out, sent = free_port(), tmp_path / "session", 200
    pid = os.fork()
    if pid == 0:  # the child: the command itself, until killed
        try:
            from motion.live.cli import run
            run({"host": "127.0.0.1", "port": port, "out_dir": str(out), "status_seconds": 0,
                 "checkpoint": "none", "head2neck": "none"})
        finally:
            os._exit(1)
    capture = out / "bob" / "capture.csv"
    try:
        deadline = time.monotonic() + 60
        while not out.is_dir() and time.monotonic() < deadline:  # made once the socket listens
            time.sleep(0.05)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for i in range(sent):
                tx.sendto(encode("phone-bob", "bob", take.frames[i], take.values[i]), ("127.0.0.1", port))
                time.sleep(0.001)
        while time.monotonic() < deadline and (not capture.is_file() or capture.read_text().count("\n") < 1 + sent):
            time.sleep(0.05)
        os.kill(pid, signal.SIGKILL)
    finally:
        os.waitpid(pid, 0)
    assert not (out / "summary.json").exists() and not (out / "bob" / "params.npz").exists()  # killed mid-session
    assert capture.read_text().count("\n") == 1 + sent
    track = read_expressions(capture)
    expected = np.stack([parse(encode("d", "s", 0, take.values[i])).psi() for i in range(sent)])
    np.testing.assert_allclose(track.time, np.arange(sent) / 60, atol=1e-9)
    np.testing.assert_allclose(track.psi, expected, atol=1e-6)
    cfg = InferConfig(expressions=str(capture), plot=False, checkpoint="none", head2neck="none")
    row = run_take(cfg, load_models(cfg, announce=lambda *_: None), str(capture), tmp_path / "offline",
                   announce=lambda *_: None)
    params = load_params(tmp_path / "offline" / "params.npz")
    assert row["frames"] == len(params) == sent  # no larynx model: the stream's own 60 fps
    np.testing.assert_allclose(params.psi, expected, atol=1e-6)
