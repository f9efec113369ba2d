"""The live view of ``python -m motion.live viewer=true`` (``motion.live.viewer_server``) over loopback.

Without a browser: the page is served at ``/``, the WebSocket handshake answers the key, a frame the receiver
runs arrives as an unmasked JSON text message equal to its params, a ping is answered, a close is echoed, a
client that never reads does not hold the receiver up.  Who may talk to it: another Origin or another Host is
refused (403); frames RFC 6455 says to close on are closed; stalled clients do not lock out the next one; a
client flooding its socket does not slow the receiver nor the other clients' frames (bounds measured here);
pipelined requests never read do not grow the server.  With Debian's ``chromium`` and Python
``playwright``: the page served over http connects to ``/ws`` and poses the character as the receiver's last
frame (bones and morphs within 1e-4).  Skipped, with the reason, where either is missing.
"""
from __future__ import annotations

import base64
import hashlib
import json
import os
import socket
import struct
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

from motion.live import viewer_server
from motion.live.cli import live_models, stream_options
from motion.live.config import LiveConfig
from motion.live.packet import encode
from motion.live.receiver import LiveReceiver
from motion.live.send.take import demo_as_take
from motion.live.viewer_server import ViewerServer, start_viewer
from tests.browser import headless_chromium
from tests.test_live_receiver import DEVICE, send_and_drain
from tests.test_viewer import TOLERANCE, theta_quaternions

GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"   # RFC 6455 section 1.3


@pytest.fixture(scope="module")
def models():
    return live_models(LiveConfig(), announce=lambda *_: None)


@pytest.fixture(scope="module")
def page(models):
    return viewer_server.live_page(models.rig, models.rig_name)


@pytest.fixture()
def live(models, page, monkeypatch):
    """(receiver, viewer server) on free loopback ports, the receiver hooked to the server."""
    monkeypatch.setattr(viewer_server, "live_page", lambda *_: page)      # built once for the module
    server, on_frame = start_viewer(models, "127.0.0.1", 0, 1.0, announce=lambda *_: None)
    rx = LiveReceiver(models, stream_options(LiveConfig()), "127.0.0.1", 0, announce=lambda *_: None,
                      on_frame=on_frame)
    yield rx, server
    rx.close()
    server.close()


def datagrams(count: int, start: int = 0) -> list[bytes]:
    take = demo_as_take()
    return [encode(DEVICE, "ana", take.frames[i], take.values[i]) for i in range(start, start + count)]


def read_exact(sock: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        assert chunk, "connection closed"
        out += chunk
    return out


def read_frame(sock: socket.socket) -> tuple[int, bytes]:
    """One server frame: (opcode, payload); server frames are final and unmasked."""
    b0, b1 = read_exact(sock, 2)
    assert b0 & 0x80 and not b1 & 0x80
    n = b1 & 0x7F
    if n == 126:
        n = struct.unpack(">H", read_exact(sock, 2))[0]
    elif n == 127:
        n = struct.unpack(">Q", read_exact(sock, 8))[0]
    return b0 & 0x0F, read_exact(sock, n)


def client_frame(payload: bytes, opcode: int, first: int | None = None) -> bytes:
    """A masked client frame (``first``: the whole first byte, to set FIN / reserved bits by hand)."""
    mask = os.urandom(4)
    n = len(payload)
    length = bytes([0x80 | n]) if n < 126 else bytes([0x80 | 126]) + struct.pack(">H", n)
    return (bytes([0x80 | opcode if first is None else first]) + length + mask
            + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))


def request_head(address, path: str = "/ws", host: str | None = None, origin: str | None = None,
                 key: str = "dGhlIHNhbXBsZSBub25jZQ==") -> bytes:
    lines = [f"GET {path} HTTP/1.1", f"Host: {host or f'{address[0]}:{address[1]}'}"]
    if path == "/ws":
        lines += ["Upgrade: websocket", "Connection: Upgrade", f"Sec-WebSocket-Key: {key}",
                  "Sec-WebSocket-Version: 13"]
    if origin is not None:
        lines.append(f"Origin: {origin}")
    return ("\r\n".join(lines) + "\r\n\r\n").encode()


def response_head(sock: socket.socket) -> tuple[int, dict]:
    head = b""
    while b"\r\n\r\n" not in head:
        head += read_exact(sock, 1)
    lines = head.decode().split("\r\n")
    fields = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
    return int(lines[0].split()[1]), fields


def handshake(address, **kwargs) -> socket.socket:
    sock = socket.create_connection(address, timeout=5)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(request_head(address, key=key, **kwargs))
    status, fields = response_head(sock)
    assert status == 101
    assert fields["sec-websocket-accept"] == base64.b64encode(hashlib.sha1(key.encode() + GUID).digest()).decode()
    return sock


def status_of(address, **kwargs) -> int:
    with socket.create_connection(address, timeout=5) as sock:
        sock.sendall(request_head(address, **kwargs))
        return response_head(sock)[0]


def test_page_handshake_and_frames_without_browser(live):
    rx, server = live
    host, port = server.address
    with urllib.request.urlopen(f"http://{host}:{port}/", timeout=10) as response:
        html = response.read().decode("utf-8")
        assert response.headers["Cache-Control"] == "no-store" and response.headers["X-Frame-Options"] == "DENY"
    assert 'id="hackneck-glb"' in html and "connectLive" in html
    header = json.loads(html.split('id="hackneck-header">')[1].split("</script>")[0])
    assert header["frames"] == 0 and "data" not in header             # live mode
    sock = handshake((host, port), origin=f"http://{host}:{port}")
    try:
        send_and_drain(rx, datagrams(5))                              # 60 -> 30 fps: output frames 0, 1, 2
        stream = rx.streams[(DEVICE, "ana")]
        assert len(stream.recorded.tau) == 3
        for k in range(3):
            opcode, payload = read_frame(sock)
            assert opcode == 0x1
            message = json.loads(payload)
            assert message["frame"] == k and abs(message["time"] - k / stream.fps) < 1e-12
            assert message["phone"] == f"{DEVICE}/ana"
            np.testing.assert_allclose(message["theta"], stream.recorded.theta[k], atol=1e-7)
            np.testing.assert_allclose(message["psi"], stream.recorded.psi[k], atol=1e-7)
            assert abs(message["tau"] - stream.recorded.tau[k]) < 1e-7 and message["eta"] == 1.0
        sock.sendall(client_frame(b"hi", 0x9))                       # ping -> pong
        assert read_frame(sock) == (0xA, b"hi")
        sock.sendall(client_frame(struct.pack(">H", 1000), 0x8))     # close -> echoed, connection closed
        assert read_frame(sock) == (0x8, struct.pack(">H", 1000))
        assert sock.recv(1) == b""
    finally:
        sock.close()


def test_unknown_path_is_404(live):
    _, server = live
    host, port = server.address
    with pytest.raises(urllib.error.HTTPError) as error:
        urllib.request.urlopen(f"http://{host}:{port}/nothing", timeout=10)
    assert error.value.code == 404


def test_another_origin_or_host_is_refused(live):
    _, server = live
    address = server.address
    own = f"http://127.0.0.1:{address[1]}"
    # cross-site WebSocket hijacking: a page elsewhere opening ws://127.0.0.1:port/ws
    for origin in ("http://evil.example", f"http://evil.example:{address[1]}", "null",
                   f"http://127.0.0.1:{address[1] + 1}", f"https://127.0.0.1:{address[1]}"):
        assert status_of(address, origin=origin) == 403, origin
    # DNS rebinding: evil.example resolving to 127.0.0.1, the browser sends its own name as Host
    for host in ("evil.example", f"evil.example:{address[1]}", f"127.0.0.1:{address[1] + 1}"):
        assert status_of(address, host=host, origin=f"http://{host}") == 403, host
        assert status_of(address, path="/", host=host) == 403, host
    # an own Host with another page's Origin, and the reverse
    assert status_of(address, host=f"localhost:{address[1]}", origin=own) == 403
    # the page's own: 101 / 200
    assert status_of(address, origin=own) == 101
    assert status_of(address, host=f"localhost:{address[1]}", origin=f"http://localhost:{address[1]}") == 101
    assert status_of(address, path="/", host=f"localhost:{address[1]}") == 200


def test_viewer_host_names_the_page():
    hosts = viewer_server.own_hosts("studio.local", 8765)
    assert hosts == {"localhost:8765", "127.0.0.1:8765", "[::1]:8765", "studio.local:8765"}
    assert viewer_server.own_hosts("0.0.0.0", 80) == {"localhost:80", "127.0.0.1:80", "[::1]:80"}
    # bound to every interface: any IP literal with the port (what DNS rebinding cannot send), no name
    assert viewer_server.is_ip_authority("192.168.1.20:8765", 8765)
    assert viewer_server.is_ip_authority("[fe80::1]:8765", 8765)
    assert not viewer_server.is_ip_authority("evil.example:8765", 8765)
    assert not viewer_server.is_ip_authority("192.168.1.20:8766", 8765)
    assert not viewer_server.is_ip_authority("fe80::1:8765", 8765)


def test_protocol_violations_are_closed(live):
    """RFC 6455 5.5: control frames <= 125 bytes and not fragmented; 5.2: reserved bits and opcodes -> fail."""
    _, server = live
    own = f"http://127.0.0.1:{server.address[1]}"
    for name, frame in {"oversized ping": client_frame(bytes(126), 0x9),
                        "fragmented ping": client_frame(b"x", 0x9, first=0x09),
                        "reserved bit": client_frame(b"x", 0x1, first=0x80 | 0x40 | 0x1),
                        "unknown opcode": client_frame(b"x", 0x3)}.items():
        sock = handshake(server.address, origin=own)
        try:
            sock.sendall(frame)
            opcode, payload = read_frame(sock)
            assert opcode == 0x8 and struct.unpack(">H", payload[:2])[0] == 1002, (name, payload)  # protocol error
            sock.sendall(client_frame(payload[:2], 0x8))
            assert sock.recv(1) == b"", name
        finally:
            sock.close()


def test_a_client_that_never_reads_does_not_hold_up_the_receiver(live):
    rx, server = live
    sock = handshake(server.address)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        started = time.monotonic()
        assert send_and_drain(rx, datagrams(600)) == 600              # 300 output frames, nobody reading
        assert time.monotonic() - started < 20
        assert len(rx.streams[(DEVICE, "ana")].recorded.tau) == 300
        assert server.thread.is_alive() and server.broadcaster.is_alive()
        assert all(len(c.outbox) <= viewer_server.CLIENT_FRAMES for c in list(server.clients))  # only the latest
    finally:
        sock.close()


def test_stalled_clients_do_not_lock_out_the_next(models, monkeypatch):
    """16 stalled clients (8 sending half a request, 8 WebSockets never reading while frames of 100 kB flow)
    and the 17th is served at once; the stalled ones are closed by their timeouts and free their slots."""
    monkeypatch.setattr(viewer_server, "SEND_TIMEOUT", 1.0)
    monkeypatch.setattr(viewer_server, "OPEN_TIMEOUT", 1.0)
    server = ViewerServer("<!doctype html>live" + "x" * (1 << 20), "127.0.0.1", 0, announce=lambda *_: None).start()
    address, own = server.address, f"http://127.0.0.1:{server.address[1]}"
    stalled, publishing = [], threading.Event()

    def publish():
        k = 0
        while not publishing.wait(0.02):
            server.publish("p/q", 30.0, k, np.zeros((8, 3)), np.zeros(25000), 0.0, 1.0)
            k += 1
    publisher = threading.Thread(target=publish)
    publisher.start()
    try:
        for _ in range(8):
            sock = socket.create_connection(address, timeout=5)
            sock.sendall(request_head(address)[:20])                    # half a request, then nothing
            stalled.append(sock)
        for _ in range(8):
            sock = handshake(address, origin=own)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # never read
            stalled.append(sock)
        time.sleep(0.3)
        assert len(server.connections) == 16
        started = time.monotonic()
        with urllib.request.urlopen(f"{own}/", timeout=5) as response:   # the 17th
            assert len(response.read()) == len(server.page)
        with socket.create_connection(address, timeout=5) as sock:
            sock.sendall(request_head(address, origin=own))
            assert response_head(sock)[0] == 101
            assert json.loads(read_frame(sock)[1])["phone"] == "p/q"
        assert time.monotonic() - started < 1.0
        # the stalled ones are dropped within their timeouts (1 s here; 5 and 10 s by default)
        deadline = time.monotonic() + 5
        while server.connections and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not server.connections and server.dropped_clients == 8
    finally:
        publishing.set()
        publisher.join()
        for sock in stalled:
            sock.close()
        server.close()


def test_connection_cap_frees_slots_of_stalled_clients(monkeypatch):
    monkeypatch.setattr(viewer_server, "MAX_CONNECTIONS", 4)
    monkeypatch.setattr(viewer_server, "OPEN_TIMEOUT", 0.5)
    server = ViewerServer("<!doctype html>live", "127.0.0.1", 0, announce=lambda *_: None).start()
    address = server.address
    stalled = [socket.create_connection(address, timeout=5) for _ in range(4)]   # never send a byte
    try:
        time.sleep(0.1)
        with socket.create_connection(address, timeout=5) as sock:               # refused while all 4 stall
            sock.sendall(request_head(address, path="/"))
            try:
                assert sock.recv(1) == b""                                       # closed unanswered
            except ConnectionResetError:
                pass                                                             # or reset: the same
        assert server.refused_connections == 1
        time.sleep(0.6)                                                          # their open timeout
        assert status_of(address, path="/") == 200
    finally:
        for sock in stalled:
            sock.close()
        server.close()


FLOODER = r"""
import base64, os, socket, sys, threading, time
host, port, seconds = sys.argv[1], int(sys.argv[2]), float(sys.argv[3])
sock = socket.create_connection((host, port))
sock.sendall((f"GET /ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
              f"Sec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}\r\nSec-WebSocket-Version: 13\r\n\r\n"
              ).encode())
head = b""
while b"\r\n\r\n" not in head:
    head += sock.recv(1)
assert head.startswith(b"HTTP/1.1 101"), head
threading.Thread(target=lambda: [None for _ in iter(lambda: sock.recv(65536), b"")], daemon=True).start()
mask = os.urandom(4)
ping = bytes([0x89, 0x80 | 125]) + mask + bytes(mask[i % 4] for i in range(125))
print("flooding", flush=True)
end = time.monotonic() + seconds
while time.monotonic() < end:
    sock.sendall(ping * 64)      # blocks while the server reads no faster
"""


def latencies(rx: LiveReceiver, server: ViewerServer, client: socket.socket, count: int, start: int):
    """Send ``count`` datagrams one at a time; (receiver ms per output frame, broadcast ms per frame: on_frame
    -> a reading client has it)."""
    stream = rx.streams.get((DEVICE, "ana"))
    before = len(stream.recorded.latency_ms) if stream else 0
    published, arrived = {}, {}
    hook = rx.on_frame

    def on_frame(stream, k):
        published[k] = time.perf_counter()
        hook(stream, k)

    def read():
        client.settimeout(2)
        try:
            while len(arrived) < count // 2:
                k = json.loads(read_frame(client)[1])["frame"]
                arrived[k] = time.perf_counter()
        except (OSError, AssertionError):
            pass
    reader = threading.Thread(target=read)
    reader.start()
    rx.on_frame = on_frame
    try:
        for data in datagrams(count, start):
            send_and_drain(rx, [data])
    finally:
        rx.on_frame = hook
    reader.join(5)
    stream = rx.streams[(DEVICE, "ana")]
    broadcast = [1e3 * (arrived[k] - published[k]) for k in published if k in arrived]
    assert len(broadcast) == len(published) == count // 2
    return np.asarray(stream.recorded.latency_ms[before:]), np.asarray(broadcast)


def test_a_flooding_client_slows_neither_the_receiver_nor_the_others(live):
    """A client in another process sending masked pings as fast as the server takes them (and reading the
    pongs): it costs the server under 8 % of a core (reads throttled to READ_RATE; ~25 % without, on a loaded
    2-core machine), and the receiver's latency (receipt -> params) and the broadcast latency (params -> a reading
    client) stay near the same measured without it (medians: this machine's load is not ours to hold)."""
    rx, server = live
    host, port = server.address
    client = handshake((host, port), origin=f"http://{host}:{port}")
    try:
        latencies(rx, server, client, 40, 0)                                   # warm up
        quiet, quiet_broadcast = latencies(rx, server, client, 120, 40)
        flooder = subprocess.Popen([sys.executable, "-c", FLOODER, host, str(port), "60"], stdout=subprocess.PIPE,
                                   text=True)
        try:
            assert flooder.stdout.readline().strip() == "flooding"
            time.sleep(0.2)
            cpu, wall = time.process_time(), time.perf_counter()
            time.sleep(1.5)                                                    # the receiver idle: the flood only
            cpu_share = (time.process_time() - cpu) / (time.perf_counter() - wall)
            flooded, flooded_broadcast = latencies(rx, server, client, 120, 160)
            alive = flooder.poll() is None
        finally:
            flooder.kill()
            flooder.wait()
    finally:
        client.close()
    assert alive, "the flood ended before the measurement did"
    p99 = {k: float(np.percentile(v, 99)) for k, v in (("quiet", quiet), ("flooded", flooded),
                                                       ("quiet_broadcast", quiet_broadcast),
                                                       ("flooded_broadcast", flooded_broadcast))}
    print(f"flood: server CPU {100 * cpu_share:.1f} % of a core; p99 ms {p99}")
    assert cpu_share < 0.08, cpu_share          # the mechanism: what the flood takes from the receiver's CPU
    # the effect, on medians: a p99 of 60 frames moves by 100 ms and more between runs when other processes load
    # the 2 cores (seen at load 10: quiet 14 ms, flooded 162 ms, the same code); the p99 figures, old server
    # against new, are benchmarks/bench_live_page.py's (the hand-written server: +40-80 ms receiver, x4-8 broadcast)
    median = {k: float(np.median(v)) for k, v in (("quiet", quiet), ("flooded", flooded),
                                                  ("quiet_broadcast", quiet_broadcast),
                                                  ("flooded_broadcast", flooded_broadcast))}
    assert median["flooded"] < 2 * median["quiet"] + 10.0, (median, p99)
    assert median["flooded_broadcast"] < 2 * median["quiet_broadcast"] + 10.0, (median, p99)


def rss_mb() -> float:
    with open("/proc/self/status") as status:
        return next(int(line.split()[1]) for line in status if line.startswith("VmRSS:")) / 1024


def test_pipelined_requests_never_read_do_not_grow_the_server(live, caplog):
    """141 pipelined GETs for the 2.5 MB page, eight times over, on four sockets that never read: one answer
    each at most (the library fails a connection whose request is followed by more bytes before it is answered;
    the rest is discarded), the server's memory bounded (the hand-written server grew by ~350 MB in 3 s)."""
    _, server = live
    address = server.address
    pipelined = request_head(address, path="/") * 141
    before = rss_mb()
    socks = []
    try:
        for _ in range(4):
            sock = socket.create_connection(address, timeout=5)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            sock.settimeout(0.5)
            try:
                for _ in range(8):
                    sock.sendall(pipelined)
            except (TimeoutError, BrokenPipeError, ConnectionResetError):
                pass                                                   # the server stopped reading or closed
            socks.append(sock)
        time.sleep(1.0)
        grown = rss_mb() - before
        answers = []
        for sock in socks:
            sock.settimeout(5)
            data = b""
            try:
                while chunk := sock.recv(1 << 20):
                    data += chunk
            except (ConnectionResetError, TimeoutError):
                pass
            answers.append(data.count(b"HTTP/1.1 200 OK"))
    finally:
        for sock in socks:
            sock.close()
    print(f"pipelined: grown {grown:.1f} MB, answers {answers}")
    assert grown < 40, f"the server grew by {grown:.0f} MB"
    assert max(answers) <= 1, answers
    # the library's error for it ("unexpected internal error", a traceback) is counted, not printed
    assert viewer_server.PEER_ERRORS.count > 0 and not [r for r in caplog.records if r.name == "motion.live.viewer"]


# ----------------------------------------------------------------------------- in a real browser


def test_browser_shows_the_receivers_last_frame(live):
    rx, server = live
    host, port = server.address
    with headless_chromium() as browser:
        page = browser.new_page(viewport={"width": 480, "height": 480})
        errors = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        page.goto(f"http://{host}:{port}/", timeout=20_000)
        page.wait_for_function("window.hackneck && (window.hackneck.ready || window.hackneck.error)",
                               timeout=20_000)
        assert page.evaluate("window.hackneck.error") is None
        page.wait_for_function("document.getElementById('status').textContent === 'live: connected'",
                               timeout=10_000)
        send_and_drain(rx, datagrams(40))
        stream = rx.streams[(DEVICE, "ana")]
        last = len(stream.recorded.tau) - 1
        assert last == 19
        page.wait_for_function(f"window.hackneck.state().frame === {last}", timeout=10_000)
        state = page.evaluate("window.hackneck.state()")
        assert abs(state["time"] - last / stream.fps) < 1e-9
        expected = theta_quaternions(stream.recorded.theta[last])
        for j, name in enumerate(rx.models.rig.joint_names):
            got = np.array(state["bones"][name])
            error = min(np.abs(got - expected[j]).max(), np.abs(got + expected[j]).max())
            assert error < TOLERANCE, (name, got, expected[j])
        morphs = np.array([state["morphs"][name] for name in rx.models.rig.expression_names])
        assert np.abs(morphs - stream.recorded.psi[last]).max() < TOLERANCE
        assert abs(state["tau"] - stream.recorded.tau[last]) < TOLERANCE and state["eta"] == 1.0
        assert np.abs(stream.recorded.theta[last]).max() > 1e-3               # a pose, not the rest
        assert not errors, errors


def test_browser_lists_the_phones_and_shows_the_one_chosen(live):
    rx, server = live
    host, port = server.address
    take = demo_as_take()
    with headless_chromium() as browser:
        page = browser.new_page(viewport={"width": 480, "height": 480})
        page.goto(f"http://{host}:{port}/", timeout=20_000)
        page.wait_for_function("window.hackneck && (window.hackneck.ready || window.hackneck.error)",
                               timeout=20_000)
        page.wait_for_function("document.getElementById('status').textContent === 'live: connected'",
                               timeout=10_000)
        # two phones at once, a frame of each per tick as they arrive: ana from the start of the take, ben
        # from four seconds in (another pose)
        for i in range(20):
            send_and_drain(rx, [encode(DEVICE, "ana", take.frames[i], take.values[i]),
                                encode("device-ben", "ben", take.frames[240 + i], take.values[240 + i])])
            time.sleep(0.005)
        page.wait_for_function("window.hackneck.phones().length === 2", timeout=10_000)
        assert page.evaluate("window.hackneck.phones()") == [f"{DEVICE}/ana", "device-ben/ben"]
        assert page.evaluate("document.getElementById('phone').value") == f"{DEVICE}/ana"   # the first seen
        page.select_option("#phone", "device-ben/ben")                     # as a user picks it
        send_and_drain(rx, [encode("device-ben", "ben", take.frames[i], take.values[i]) for i in range(260, 264)])
        stream = rx.streams[("device-ben", "ben")]
        last = len(stream.recorded.tau) - 1
        page.wait_for_function(f"window.hackneck.state().frame === {last}", timeout=10_000)
        state = page.evaluate("window.hackneck.state()")
        expected = theta_quaternions(stream.recorded.theta[last])
        for j, name in enumerate(rx.models.rig.joint_names):
            got = np.array(state["bones"][name])
            assert min(np.abs(got - expected[j]).max(), np.abs(got + expected[j]).max()) < TOLERANCE, name
        ana = rx.streams[(DEVICE, "ana")]
        assert np.abs(ana.recorded.theta[-1] - stream.recorded.theta[last]).max() > 1e-3   # ben's, not ana's
