"""motion.live over loopback: bad datagrams counted and the stream going on, a garbage flood with bounded
state, streaming equal to the offline pipeline on the recorded capture.csv, and the command itself."""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import tracemalloc

import numpy as np
import pytest

from data.params import load_params
from motion.live.cli import finish, live_models, stream_options
from motion.live.config import LiveConfig
from motion.live.packet import encode
from motion.live.receiver import LiveReceiver
from motion.live.send.take import demo_as_take
from motion.pipeline.config import InferConfig
from motion.pipeline.models import load_models
from motion.pipeline.take import run_take
from tests.conftest import REPO
from tests.test_live_packet import REASON, malformed

DEVICE = "6C3A2E5F-0000-4000-8000-000000000001"


@pytest.fixture(scope="module")
def models():
    return live_models(LiveConfig(), announce=lambda *_: None)


@pytest.fixture()
def receiver(models):
    rx = LiveReceiver(models, stream_options(LiveConfig()), "127.0.0.1", 0, max_phones=4, announce=lambda *_: None)
    yield rx
    rx.close()


_SENDERS: dict[tuple[int, str], socket.socket] = {}  # one phone = one source address (streams are bound to it)


def sender(rx: LiveReceiver, source: str = "127.0.0.1") -> socket.socket:
    """The socket a test's phone sends to ``rx`` from (the same one for every call: the same address)."""
    key = (id(rx), source)
    if key not in _SENDERS:
        tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        tx.bind((source, 0))
        _SENDERS[key] = tx
    return _SENDERS[key]


def send_and_drain(rx: LiveReceiver, datagrams: list[bytes], timeout: float = 10.0, source: str = "127.0.0.1") -> int:
    """Send over loopback from ``source`` in small batches (the kernel buffer may be small), draining after
    each; handled."""
    handled, deadline = 0, time.monotonic() + timeout
    tx = sender(rx, source)
    for start in range(0, len(datagrams), 100):
        batch = datagrams[start:start + 100]
        for data in batch:
            tx.sendto(data, rx.address)
        target = handled + len(batch)
        while handled < target and time.monotonic() < deadline:
            if rx.wait(0.05):
                handled += rx.drain()
    return handled


def test_bad_datagrams_counted_stream_goes_on(receiver):
    take = demo_as_take()
    good = [encode(DEVICE, "ana", take.frames[i], take.values[i]) for i in range(12)]
    bad = [data for data, _ in malformed().values()]
    late = encode(DEVICE, "ana", take.frames[3], take.values[3])
    clamped_values = take.values[10].copy()
    clamped_values[17] = 1.7  # JawOpen above WEIGHT_RANGE: clamped and counted, not refused
    sequence = good[:4] + bad + [late] + good[4:10] + [encode(DEVICE, "ana", take.frames[10], clamped_values)]
    assert send_and_drain(receiver, sequence) == len(sequence)
    expected = {}
    for kind in REASON:
        expected[REASON[kind]] = expected.get(REASON[kind], 0) + 1
    expected["late"] = 1
    assert dict(receiver.rejected) == expected
    stream = receiver.streams[(DEVICE, "ana")]
    assert stream.recorded.frames == 11 and stream.last_frame == int(take.frames[10])
    assert stream.late == 1 and stream.clamped == 1 and stream.missing == 0
    assert len(stream.recorded.tau) == 6  # 60 -> 30 fps: frames 0, 2, ..., 10
    assert max(float(v) for v in stream.rows[-1].split(",")[2:54]) == pytest.approx(1.5)  # capture.csv's row


def test_garbage_flood_bounded(receiver):
    rng = np.random.default_rng(1)
    take = demo_as_take()
    warm = [encode(DEVICE, "ana", take.frames[i], take.values[i]) for i in range(2)]
    send_and_drain(receiver, warm)
    garbage = [rng.bytes(int(n)) for n in rng.integers(0, 400, 10_000)]
    garbage[::7] = [bytes([6]) + g[1:] for g in garbage[::7]]  # past the version check
    new_phones = [encode(f"device-{k}", "x", 1000 + k, take.values[0]) for k in range(50)]
    tracemalloc.start()
    before = tracemalloc.take_snapshot()
    assert send_and_drain(receiver, garbage + new_phones, timeout=30.0) == len(garbage) + len(new_phones)
    grown = sum(s.size_diff for s in tracemalloc.take_snapshot().compare_to(before, "filename"))
    tracemalloc.stop()
    assert receiver.state_size()["streams"] == 4  # max_phones: the 47 further phones refused
    assert receiver.rejected["too_many_phones"] == 47
    assert sum(receiver.rejected.values()) == 10_000 + 47
    assert grown < 2_000_000, f"{grown} bytes kept after the flood"  # 3 phones' few frames, no per-datagram state
    produced = send_and_drain(receiver, [encode(DEVICE, "ana", take.frames[2], take.values[2])])
    assert produced == 1 and len(receiver.streams[(DEVICE, "ana")].recorded.tau) == 2


def test_streaming_equals_offline(receiver, models, tmp_path):
    take = demo_as_take()
    keep = [i for i in range(300) if i not in (61, 62, 63, 150)]  # gaps by frame number, filled
    datagrams = [encode(DEVICE, "ana", take.frames[i], take.values[i]) for i in keep]
    datagrams.insert(100, datagrams[90])  # a late duplicate, dropped
    send_and_drain(receiver, datagrams)
    summary = finish(receiver, tmp_path / "live", 1.0)
    subject = summary["subjects"]["ana"]
    assert subject["frames"] == len(keep) and subject["missing_frames"] == 4 and summary["rejected"] == {"late": 1}
    assert set(subject["latency_ms"]) == {"p50", "p99", "max"}
    live = load_params(tmp_path / "live" / "ana" / "params.npz")
    capture = tmp_path / "live" / "ana" / "capture.csv"
    offline_cfg = InferConfig(expressions=str(capture), plot=False)
    run_take(offline_cfg, load_models(offline_cfg, announce=lambda *_: None), str(capture), tmp_path / "offline",
             announce=lambda *_: None)
    offline = load_params(tmp_path / "offline" / "params.npz")
    assert len(live) == len(offline) == 150 and live.fps == offline.fps == 30.0
    np.testing.assert_allclose(live.time, offline.time, atol=1e-9)
    np.testing.assert_allclose(live.psi, offline.psi, atol=1e-6)
    np.testing.assert_allclose(live.tau, offline.tau, atol=1e-5)
    np.testing.assert_allclose(live.theta, offline.theta, atol=1e-5)
    assert np.abs(live.theta).max() > 0.01 and np.ptp(live.tau) > 0  # the take moves the neck and larynx


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_command_line_session(tmp_path):
    port = free_port()
    out = tmp_path / "session"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    process = subprocess.Popen([sys.executable, "-m", "motion.live", "host=127.0.0.1", f"port={port}",
                                f"out_dir={out}", "duration=60", "status_seconds=0"], cwd=REPO, env=env,
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        line = ""
        while "listening" not in line and time.monotonic() < deadline:
            line = process.stdout.readline()
        assert "listening" in line, process.stderr.read()
        sent = subprocess.run([sys.executable, "-m", "motion.live.send", "take=demo", "host=127.0.0.1",
                               f"port={port}", "speed=4", "subject=bob"], cwd=REPO, env=env, capture_output=True,
                              text=True, timeout=60)
        assert sent.returncode == 0, sent.stderr
        time.sleep(0.5)
        process.send_signal(2)  # SIGINT: stop and write
        stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
    assert process.returncode == 0, stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["subjects"]["bob"]["frames"] == 720 and summary["rejected"] == {}
    assert len(load_params(out / "bob" / "params.npz")) == 360


SAMPLE = REPO.parent / "shared" / "samples" / "livelinkface" / "apfel.csv"


@pytest.mark.skipif(not SAMPLE.is_file(), reason=f"Live Link Face sample not found at {SAMPLE}")
def test_real_capture_replayed_reads_back(tmp_path):
    """A real Live Link Face CSV (its own column order, fractional timecode frames, lost-tracking rows) sent by
    the sender's reader and recorded: capture.csv reads back as the same take."""
    from data.expressions import read_expressions
    from motion.live.send import read_take

    lines = SAMPLE.read_text().splitlines()[:401]
    original = tmp_path / "take.csv"
    original.write_text("\n".join(lines) + "\n")
    take = read_take(str(original))
    light = live_models(LiveConfig(checkpoint="none", head2neck="none"), announce=lambda *_: None)
    rx = LiveReceiver(light, stream_options(LiveConfig()), "127.0.0.1", 0, announce=lambda *_: None)
    try:
        datagrams = [encode(DEVICE, "apfel", f, v, s, (take.rate, 1))
                     for f, s, v in zip(take.frames, take.subframes, take.values)]
        send_and_drain(rx, datagrams)
        finish(rx, tmp_path / "live", 1.0)
    finally:
        rx.close()
    before = read_expressions(original)
    after = read_expressions(tmp_path / "live" / "apfel" / "capture.csv")
    lost = sum(1 for line in lines[1:] if line.endswith(",0") and line.count(",") == 1)
    assert len(after) >= len(before) == 400 - lost  # gaps filled in the recording
    kept = np.isin(np.round(after.time, 6), np.round(before.time, 6))
    assert kept.sum() == len(before)
    np.testing.assert_allclose(after.time[kept], before.time, atol=1e-9)
    np.testing.assert_allclose(after.psi[kept], before.psi, atol=1e-6)
    if before.head_ypr is None:  # this sample has no head rotation recorded (all zero)
        assert after.head_ypr is None
    else:
        np.testing.assert_allclose(after.head_ypr[kept], before.head_ypr, atol=1e-6)


def test_jump_and_rate_change_refused(receiver):
    take = demo_as_take()
    now = time.perf_counter_ns()
    for i in range(4):
        receiver.handle(encode(DEVICE, "ana", take.frames[i], take.values[i]), now)
    receiver.handle(encode(DEVICE, "ana", take.frames[3] + 60 * 11, take.values[4]), now)  # > max_gap_seconds
    receiver.handle(encode(DEVICE, "ana", take.frames[4], take.values[4], rate=(30, 1)), now)
    receiver.handle(encode(DEVICE, "ana", take.frames[3] + 60 * 9, take.values[4]), now)  # a 9 s gap: filled
    assert receiver.flush() == 2  # frames 0 and 2 run; the 9 s gap is held (the gap rule): nothing run
    assert dict(receiver.rejected) == {"jump": 1, "rate": 1}
    stream = receiver.streams[(DEVICE, "ana")]
    assert stream.missing == 60 * 9 - 1 and stream.gaps == 1
    assert len(stream.recorded.tau) == 272 and stream.recorded.held == 270  # the grid up to 9.05 s (271.5 frames)
    assert stream.recorded.tau[2:] == [stream.recorded.tau[1]] * 270


def test_allow_idle_and_failure_isolated(models, tmp_path):
    """allow= refuses other senders unread; an idle stream is closed and written, freeing its slot; a stream
    that raises is closed with its reason and what it received, the other goes on."""
    from motion.live.outputs import SessionWriter

    take = demo_as_take()
    walled = LiveReceiver(models, stream_options(LiveConfig()), "127.0.0.1", 0, announce=lambda *_: None,
                          allow=["10.0.0.0/8", "192.168.1.20"])
    try:
        assert send_and_drain(walled, [encode(DEVICE, "ana", take.frames[0], take.values[0])]) == 1
        assert dict(walled.rejected) == {"not_allowed": 1} and not walled.streams
    finally:
        walled.close()
    out = tmp_path / "live"
    out.mkdir()
    rx = LiveReceiver(models, stream_options(LiveConfig()), "127.0.0.1", 0, max_phones=2, announce=lambda *_: None,
                      writer=SessionWriter(out, 1.0), idle_seconds=5.0)
    try:
        now, address = time.perf_counter_ns(), ("127.0.0.1", 40000)
        for i in range(6):
            rx.handle(encode(DEVICE, "ana", take.frames[i], take.values[i]), now, address)
            rx.handle(encode("device-ben", "ben", take.frames[i], take.values[i]), now, ("127.0.0.1", 40001))
        rx.flush()
        rx.streams[("device-ben", "ben")].accept = lambda *_: 1 / 0  # a bug in one stream
        rx.handle(encode("device-ben", "ben", take.frames[6], take.values[6]), now, ("127.0.0.1", 40001))
        rx.handle(encode(DEVICE, "ana", take.frames[6], take.values[6]), now, address)
        rx.flush()
        assert list(rx.streams) == [(DEVICE, "ana")] and rx.rejected["stream_error"] == 1
        spoof = encode(DEVICE, "ana", take.frames[100], take.values[7])  # a later frame, from another port
        assert rx.handle(spoof, now, ("127.0.0.1", 49999)) == 0 and rx.rejected["address"] == 1
        assert rx.streams[(DEVICE, "ana")].last_frame == int(take.frames[6])  # the phone's stream untouched
        assert rx.expire(now + 4_000_000_000) == 0 and rx.expire(now + 6_000_000_000) == 1 and not rx.streams
        assert rx.handle(encode(DEVICE, "ana", take.frames[0], take.values[0]), now, ("127.0.0.1", 40002)) == 1
        assert rx.streams[(DEVICE, "ana")].folder == "ana-6C3A2E5F-0000-4000-8000-000000000001"  # a new stream
    finally:
        rx.close()
    ben = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else None
    assert ben is None  # summary.json only at stop; the closed streams' params are already there
    assert len(load_params(out / "ben" / "params.npz")) == 3 and len(load_params(out / "ana" / "params.npz")) == 4
    assert (out / "ben" / "capture.csv").read_text().count("\n") == 1 + 6


def test_names_safe():
    """Control characters escaped in what is printed; subjects that clean to one folder name get distinct ones."""
    from motion.live.outputs import FolderNames, printable

    assert printable("\x1b[2Jred\x07") == "\\x1b[2Jred\\x07" and printable("\u202eevil") == "\\u202eevil"
    assert printable("a" * 300, 10) == "a" * 10 + "..."
    names = FolderNames()
    taken = [names.take(subject, device) for subject, device in
             [("a/b", "d1"), ("a_b", "d2"), ("A_B", "d3"), ("a_b", "d2"), ("summary.json", "d4"), ("../..", "d5"),
              ("x" * 300, "d6")]]
    assert taken[:3] == ["a_b", "a_b-d2", "A_B-d3"] and taken[3] == "a_b-2"
    assert taken[4] == "summary.json-d4" and taken[5] == "_" and len(taken[6]) == 48
    assert len({t.lower() for t in taken}) == len(taken)
