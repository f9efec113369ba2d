"""The live view of ``python -m motion.live viewer=true`` (``motion.live.viewer_server``) over loopback.

Without a browser: the page is served at ``/``, the WebSocket handshake (RFC 6455) answers the key, a frame
the receiver runs arrives as an unmasked JSON text message equal to its params, a ping is answered, a close
is echoed, and a client that never reads does not hold the receiver up.  With Debian's ``chromium`` and
Python ``playwright``: the page served over http connects to ``/ws`` and poses the character as the
receiver's last frame (bones and morphs within 1e-4).  Skipped, with the reason, where either is missing.
"""
from __future__ import annotations

import base64
import json
import os
import socket
import struct
import time
import urllib.error
import urllib.request

import numpy as np
import pytest

from motion.live.cli import live_models, stream_options
from motion.live.config import LiveConfig
from motion.live.packet import encode
from motion.live.receiver import LiveReceiver
from motion.live.send.take import demo_as_take
from motion.live.viewer_server import accept_key, start_viewer
from tests.browser import headless_chromium
from tests.test_live_receiver import DEVICE, send_and_drain
from tests.test_viewer import TOLERANCE, theta_quaternions


@pytest.fixture(scope="module")
def models():
    return live_models(LiveConfig(), announce=lambda *_: None)


@pytest.fixture()
def live(models):
    """(receiver, viewer server) on free loopback ports, the receiver hooked to the server."""
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


def client_frame(payload: bytes, opcode: int) -> bytes:
    mask = os.urandom(4)
    return bytes([0x80 | opcode, 0x80 | len(payload)]) + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))


def handshake(address) -> socket.socket:
    sock = socket.create_connection(address, timeout=5)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall(f"GET /ws HTTP/1.1\r\nHost: {address[0]}:{address[1]}\r\nUpgrade: websocket\r\n"
                 f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n".encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += read_exact(sock, 1)
    lines = head.decode().split("\r\n")
    assert lines[0].startswith("HTTP/1.1 101")
    fields = {k.lower(): v.strip() for k, _, v in (line.partition(":") for line in lines[1:] if line)}
    assert fields["sec-websocket-accept"] == accept_key(key)
    return sock


def test_accept_key_is_rfc6455():
    # the example of RFC 6455 section 1.3
    assert accept_key("dGhlIHNhbXBsZSBub25jZQ==") == "s3pPLMBiTxaQ9kYGzzhZRbK+xOo="


def test_page_handshake_and_frames_without_browser(live):
    rx, server = live
    host, port = server.address
    with urllib.request.urlopen(f"http://{host}:{port}/", timeout=10) as response:
        html = response.read().decode("utf-8")
    assert 'id="hackneck-glb"' in html and "connectLive" in html
    header = json.loads(html.split('id="hackneck-header">')[1].split("</script>")[0])
    assert header["frames"] == 0 and "data" not in header             # live mode
    sock = handshake((host, port))
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


def test_a_client_that_never_reads_does_not_hold_up_the_receiver(live):
    rx, server = live
    sock = handshake(server.address)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    try:
        started = time.monotonic()
        assert send_and_drain(rx, datagrams(600)) == 600              # 300 output frames, nobody reading
        assert time.monotonic() - started < 20
        assert len(rx.streams[(DEVICE, "ana")].recorded.tau) == 300
        assert server.thread.is_alive()
        assert all(len(c.queue) <= c.queue.maxlen for c in list(server.clients.values()))  # only the latest
    finally:
        sock.close()


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
