"""The UDP receiver: a non-blocking socket drained every tick, each datagram parsed and routed to its phone's
stream, everything refused counted by reason, with bounded state whatever arrives.

What the network can do to it (issue 59), and what stops it:
- a datagram's fields out of range: refused by ``packet.parse`` and ``PhoneStream.check`` before anything
  uses them (rate 1..240 fps, sub-frame in [0,1), frame of the day, jumps, the capture clock ahead of ours);
- a datagram that costs: at most ``max_frames_per_datagram`` output frames a stream, the models run on at
  most ``GAP_SECONDS * fps + 1`` of them (a gap is held, not computed: ``motion.live.stream``);
- a stream that raises (a bug, a full disk): closed with its reason and what it received, the others go on;
- hijack: a device id is bound to the address (IP and port) of its first datagram; the same id from another
  address is refused (``address``) until the stream expires;
- squatting: streams idle for ``idle_seconds`` expire and free their slot (what they received is written);
  ``allow`` (addresses or networks) refuses every other sender (``not_allowed``) before its datagram is read;
- names: printed through ``outputs.printable``, folders through ``outputs.FolderNames``.

Bounded: the reasons are a fixed set (one counter each), at most ``max_phones`` streams at once and
``MAX_STREAMS_PER_PHONE_SLOT * max_phones`` in a session (more: ``too_many_phones``), names at most
``packet.MAX_NAME_BYTES`` bytes, the versions announced as refused at most 256.  What grows is the recording
of output frames, no faster than real time per stream (``max_lead_seconds``).
"""
from __future__ import annotations

import ipaddress
import select
import socket
import time
from collections import Counter

import numpy as np

from motion.live.config import parse_allow
from motion.live.outputs import SessionWriter, printable
from motion.live.packet import PacketError, parse
from motion.live.stream import PhoneStream, StreamOptions, run_pending
from motion.pipeline.models import Models

RECEIVE_BUFFER = 4 << 20  # bytes of kernel buffer asked for: ~15 s of one phone at 60 fps (~300 B a datagram)
MAX_DATAGRAM = 2048       # a v6 datagram is 26 + 4 * 61 + two names (each <= 256 B): <= 782 bytes
MAX_STREAMS_PER_PHONE_SLOT = 16  # streams a session may start, per slot (each a folder on disk)


class LiveReceiver:
    """Receive Live Link Face v6 datagrams on ``host:port`` and drive one :class:`PhoneStream` per phone;
    with ``writer`` (:class:`SessionWriter`) each stream's files are written as it goes."""

    def __init__(self, models: Models, options: StreamOptions, host: str = "0.0.0.0", port: int = 11111,
                 max_phones: int = 8, absurd_weight: float = 10.0, announce=print, on_frame=None,
                 writer: SessionWriter | None = None, allow=None, idle_seconds: float = 10.0):
        self.models, self.options = models, options
        self.on_frame = on_frame  # called (stream, output index) after each output frame is run (live view)
        self.max_phones, self.absurd_weight, self.announce = max_phones, absurd_weight, announce
        self.writer, self.allow, self.idle_seconds = writer, parse_allow(allow), idle_seconds
        self.streams: dict[tuple[str, str], PhoneStream] = {}
        self.owners: dict[str, tuple[str, int]] = {}  # device id -> the address its streams are bound to
        self.closed: list[dict] = []                  # summaries of the streams closed (idle, error)
        self.started = 0
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

    def allowed(self, address) -> bool:
        if not self.allow:
            return True
        try:
            ip = ipaddress.ip_address(address[0])
        except (ValueError, TypeError, IndexError):
            return False
        return any(ip in network for network in self.allow)

    def handle(self, data: bytes, received_ns: int, address: tuple[str, int] | None = None) -> int:
        """One datagram from ``address``: the number of output frames it completed, queued for :meth:`flush`
        (0 when refused; counted by reason)."""
        self.received += 1
        if address is not None and not self.allowed(address):
            self.rejected["not_allowed"] += 1
            return 0
        stream = None
        try:
            frame = parse(data, self.absurd_weight)
            owner = self.owners.get(frame.device)
            if owner is not None and address is not None and owner != address:
                raise PacketError("address", 1, f"device {printable(frame.device, 40)} from {address[0]}:"
                                                f"{address[1]}, bound to {owner[0]}:{owner[1]}")
            stream = self.streams.get((frame.device, frame.subject))
            if stream is None:
                stream = self.start(frame, received_ns, address)
            produced = stream.accept(frame, received_ns)
        except PacketError as e:
            self.rejected[e.reason] += 1
            if e.reason == "version" and data[0] not in self.refused_versions:
                self.refused_versions.add(data[0])
                self.announce(f"live: refused packet version {data[0]}: expected 6 (Live Link Face 'ARKit' "
                              f"mode; MetaHuman Animator mode is another protocol)")
            return 0
        except Exception as e:  # noqa: BLE001 -- a stream that raises is closed; the receiver goes on
            self.rejected["stream_error"] += 1
            if stream is not None and stream.key in self.streams:
                self.close_stream(stream, f"error: {type(e).__name__}: {e}")
            return 0
        self.produced += produced
        return produced

    def start(self, frame, received_ns: int, address) -> PhoneStream:
        """A new stream for ``frame``'s phone (PacketError, nothing kept, when it cannot be one)."""
        if len(self.streams) >= self.max_phones or self.started >= MAX_STREAMS_PER_PHONE_SLOT * self.max_phones:
            raise PacketError("too_many_phones", 1, f"device {printable(frame.device, 40)} subject "
                                                    f"{printable(frame.subject, 40)}: already {len(self.streams)} "
                                                    f"phones (max_phones), {self.started} streams this session")
        stream = PhoneStream(frame.device, frame.subject, frame.rate, self.models, self.options, address)
        stream.check(frame, received_ns)  # a first frame the stream refuses makes no stream
        if self.writer is not None:
            self.writer.open(stream)
        self.streams[stream.key] = stream
        self.started += 1
        if address is not None:
            self.owners[frame.device] = address
        where = f" from {address[0]}:{address[1]}" if address else ""
        self.announce(f"live: new phone{where}: device {printable(frame.device)}, subject "
                      f"'{printable(frame.subject)}', {frame.fps:g} fps" +
                      (f" -> {stream.folder}/" if stream.folder else ""))
        return stream

    def close_stream(self, stream: PhoneStream, reason: str) -> dict | None:
        """Take a stream out (its slot and its device id's binding freed), written when there is a writer."""
        self.streams.pop(stream.key, None)
        if not any(s.device == stream.device for s in self.streams.values()):
            self.owners.pop(stream.device, None)
        stream.closed = stream.closed or reason
        stream.pending.clear()
        self.announce(f"live: closed device {printable(stream.device)}, subject '{printable(stream.subject)}' "
                      f"({printable(reason, 200)}): {stream.recorded.frames} frames")
        entry = self.writer.close(stream, reason) if self.writer is not None else None
        self.closed.append(entry or {"device": stream.device, "subject": stream.subject, "closed": reason})
        return entry

    def close_all(self, reason: str = "stop") -> None:
        for stream in list(self.streams.values()):
            self.close_stream(stream, reason)

    def expire(self, now_ns: int | None = None) -> int:
        """Close the streams with no accepted frame for ``idle_seconds``; how many."""
        now_ns = time.perf_counter_ns() if now_ns is None else now_ns
        idle = [s for s in self.streams.values()
                if s.last_ns is not None and (now_ns - s.last_ns) / 1e9 > self.idle_seconds]
        for stream in idle:
            self.close_stream(stream, f"idle for over {self.idle_seconds:g} s")
        return len(idle)

    def idle(self) -> bool:
        """Work done ahead while nothing arrives: one stream's larynx restart made ready (``prepare``)."""
        return any(stream.prepare() for stream in self.streams.values())

    def flush(self) -> int:
        """Run the output frames the handled datagrams completed (``stream.run_pending``) and write the new
        capture.csv rows; how many frames ran.  A stream that fails in either is closed."""
        streams = list(self.streams.values())
        failed: dict = {}
        ran = run_pending(streams, self.models, self.options, failed)
        if self.writer is not None:
            for stream in streams:
                try:
                    self.writer.append(stream)
                except OSError as e:
                    failed[stream.key] = f"capture.csv: {e}"
        for stream in streams:
            if stream.key in failed:
                self.rejected["stream_error"] += 1
                self.close_stream(stream, f"error: {failed[stream.key]}")
        if self.on_frame is not None and ran:
            try:
                for stream, k in ran:
                    self.on_frame(stream, k)
            except Exception:  # noqa: BLE001 -- the live view must never stop the receiver
                pass
        return len(ran)

    def drain(self, limit: int = 10000, batch: int = 64) -> int:
        """Handle every datagram waiting on the socket (at most ``limit``), running the output frames they
        complete at the end and every ``batch`` frames on the way; the number of datagrams handled."""
        handled = queued = 0
        while handled < limit:
            try:
                data, address = self.sock.recvfrom(MAX_DATAGRAM)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:  # e.g. an ICMP error reported on a UDP socket: the next datagram may be fine
                self.rejected["socket_error"] += 1
                break
            queued += self.handle(data, time.perf_counter_ns(), address)
            handled += 1
            if queued >= batch:
                self.flush()
                queued = 0
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
        """Drain the socket every tick until ``should_stop()`` or ``duration`` seconds, expiring idle streams;
        a status line every ``status_seconds`` (frames/s, rejected, latency)."""
        start = time.monotonic()
        last_status, last_received = start, 0
        while not should_stop():
            now = time.monotonic()
            if duration is not None and now - start >= duration:
                break
            if self.wait(tick):
                self.drain()
            else:
                self.idle()
            self.expire()
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
        return {"streams": len(self.streams), "owners": len(self.owners), "reasons": len(self.rejected),
                "versions": len(self.refused_versions), "closed": len(self.closed)}
