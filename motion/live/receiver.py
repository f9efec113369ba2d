"""The UDP receiver: a non-blocking socket drained every tick, each datagram parsed and routed to its phone's
stream, everything refused counted by reason, with bounded state whatever arrives.

Bounded: the reasons are a fixed set (one counter each), at most ``max_phones`` streams exist (a new phone
beyond them is refused as ``too_many_phones``), names are at most ``packet.MAX_NAME_BYTES`` bytes, the
versions announced as refused are at most 256.  What grows is the recording of accepted frames, as long as
the session lasts.
"""
from __future__ import annotations

import select
import socket
import time
from collections import Counter

import numpy as np

from motion.live.packet import PacketError, parse
from motion.live.stream import PhoneStream, StreamOptions, run_pending
from motion.pipeline.models import Models

RECEIVE_BUFFER = 4 << 20  # bytes of kernel buffer asked for: ~15 s of one phone at 60 fps (~300 B a datagram)
MAX_DATAGRAM = 2048       # a v6 datagram is 26 + 4 * 61 + two names (each <= 256 B): <= 782 bytes


class LiveReceiver:
    """Receive Live Link Face v6 datagrams on ``host:port`` and drive one :class:`PhoneStream` per phone."""

    def __init__(self, models: Models, options: StreamOptions, host: str = "0.0.0.0", port: int = 11111,
                 max_phones: int = 8, absurd_weight: float = 10.0, announce=print, on_frame=None):
        self.models, self.options = models, options
        self.on_frame = on_frame  # called (stream, output index) after each output frame is run (live view)
        self.max_phones, self.absurd_weight, self.announce = max_phones, absurd_weight, announce
        self.streams: dict[tuple[str, str], PhoneStream] = {}
        self.rejected: Counter = Counter()
        self.refused_versions: set[int] = set()
        self.received = self.produced = 0
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
        except OSError:  # the kernel caps it (net.core.rmem_max): the default buffer serves
            pass
        self.sock.bind((host, port))
        self.sock.setblocking(False)

    @property
    def address(self) -> tuple[str, int]:
        return self.sock.getsockname()

    def close(self) -> None:
        self.sock.close()

    def handle(self, data: bytes, received_ns: int) -> int:
        """One datagram: the number of output frames it completed, queued for :meth:`flush` (0 when refused;
        counted by reason)."""
        self.received += 1
        try:
            frame = parse(data, self.absurd_weight)
            stream = self.streams.get((frame.device, frame.subject))
            if stream is None:
                if len(self.streams) >= self.max_phones:
                    raise PacketError("too_many_phones", 1, f"device {frame.device[:40]!r} subject "
                                      f"{frame.subject[:40]!r}: already {self.max_phones} phones (max_phones)")
                stream = PhoneStream(frame.device, frame.subject, frame.rate, self.models, self.options)
                stream.check(frame)  # a first frame the stream refuses makes no stream
                self.streams[stream.key] = stream
                self.announce(f"live: new phone: device {frame.device}, subject '{frame.subject}', "
                              f"{frame.fps:g} fps")
            produced = stream.accept(frame, received_ns)
        except PacketError as e:
            self.rejected[e.reason] += 1
            if e.reason == "version" and data[0] not in self.refused_versions:
                self.refused_versions.add(data[0])
                self.announce(f"live: refused packet version {data[0]}: expected 6 (Live Link Face 'ARKit' "
                              f"mode; MetaHuman Animator mode is another protocol)")
            return 0
        self.produced += produced
        return produced

    def flush(self) -> int:
        """Run the output frames the handled datagrams completed (``stream.run_pending``); how many."""
        streams = list(self.streams.values())
        if self.on_frame is None:
            return run_pending(streams, self.models, self.options)
        before = [len(s.recorded.tau) for s in streams]
        done = run_pending(streams, self.models, self.options)
        if done:
            try:
                for stream, start in zip(streams, before):
                    for k in range(start, len(stream.recorded.tau)):
                        self.on_frame(stream, k)
            except Exception:  # noqa: BLE001 -- the live view must never stop the receiver
                pass
        return done

    def drain(self, limit: int = 10000, batch: int = 64) -> int:
        """Handle every datagram waiting on the socket (at most ``limit``), running the output frames they
        complete at the end and every ``batch`` frames on the way; the number of datagrams handled."""
        handled = queued = 0
        while handled < limit:
            try:
                data = self.sock.recv(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. an ICMP error reported on a UDP socket: the next datagram may be fine
                self.rejected["socket_error"] += 1
                break
            queued += self.handle(data, time.perf_counter_ns())
            handled += 1
            if queued >= batch:
                queued -= self.flush()
        self.flush()
        return handled

    def wait(self, timeout: float) -> bool:
        """Wait up to ``timeout`` seconds for a datagram; whether one is there."""
        try:
            ready, _, _ = select.select([self.sock], [], [], max(timeout, 0.0))
        except InterruptedError:
            return False
        return bool(ready)

    def run(self, duration: float | None, should_stop, tick: float = 0.002, status_seconds: float = 5.0) -> None:
        """Drain the socket every tick until ``should_stop()`` or ``duration`` seconds; a status line every
        ``status_seconds`` (frames/s, rejected, latency)."""
        start = time.monotonic()
        last_status, last_received = start, 0
        while not should_stop():
            now = time.monotonic()
            if duration is not None and now - start >= duration:
                break
            if self.wait(tick):
                self.drain()
            if status_seconds and now - last_status >= status_seconds:
                self.announce(self.status_line((self.received - last_received) / (now - last_status)))
                last_status, last_received = now, self.received

    def status_line(self, rate: float) -> str:
        recent = [v for s in self.streams.values() for v in s.recorded.latency_ms[-300:]]
        latency = (f"latency p50 {np.percentile(recent, 50):.2f} ms p99 {np.percentile(recent, 99):.2f} ms"
                   if recent else "latency -")
        return (f"live: {len(self.streams)} phone(s), {rate:.1f} datagrams/s, {self.produced} frames out, "
                f"rejected {sum(self.rejected.values())}, {latency}")

    def state_size(self) -> dict:
        """What the receiver holds apart from recordings: for the memory-bound tests."""
        return {"streams": len(self.streams), "reasons": len(self.rejected), "versions": len(self.refused_versions)}
