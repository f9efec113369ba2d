"""The live view of ``python -m motion.live viewer=true``: an HTTP + WebSocket server in a background thread.

``GET /`` returns the viewer page (``scene.viewer``) with the rig's GLB and no clip (the page starts in live
mode); ``GET /ws`` upgrades to a WebSocket (the server side of RFC 6455, stdlib only) on which every output
frame is sent as a JSON text message ``{phone, time, frame, theta [J][3], psi [E], tau, eta}``.

The receiver only calls :meth:`ViewerServer.publish` (append to a bounded deque: never blocks, never
raises); the thread encodes and sends.  Each browser has a bounded queue keeping only the latest frames; a
browser that does not read for ``STALL_SECONDS`` or misbehaves is dropped.  Anything going wrong in the
thread stops the live view (announced), never the receiver.
"""
from __future__ import annotations

import base64
import hashlib
import json
import selectors
import socket
import struct
import threading
import time
from collections import deque

import numpy as np

from data.params import AnimationParams, rig_checksum
from scene.viewer.build import clip_header, glb_bytes, render_page

GUID = b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11"
INBOX = 256               # frames waiting for the thread (all phones); older ones are dropped
CLIENT_FRAMES = 8         # messages queued per browser; older ones are dropped (the latest kept)
MAX_CLIENTS = 16
MAX_REQUEST = 16 << 10    # bytes of an HTTP request head
MAX_CLIENT_FRAME = 1 << 16  # bytes of a message from a browser (it sends none but close / ping / pong)
STALL_SECONDS = 10.0      # a browser that takes nothing for this long with data pending is dropped
LIVE_TAU_RANGE = (-0.1, 0.1)  # the larynx targets of the live GLB span this tau range (clamped beyond)


def accept_key(key: str) -> str:
    """Sec-WebSocket-Accept of a Sec-WebSocket-Key (RFC 6455 section 4.2.2)."""
    return base64.b64encode(hashlib.sha1(key.strip().encode("ascii") + GUID).digest()).decode("ascii")


def ws_frame(payload: bytes, opcode: int = 0x1) -> bytes:
    """One unmasked, final server frame."""
    n = len(payload)
    if n < 126:
        head = struct.pack(">BB", 0x80 | opcode, n)
    elif n < 1 << 16:
        head = struct.pack(">BBH", 0x80 | opcode, 126, n)
    else:
        head = struct.pack(">BBQ", 0x80 | opcode, 127, n)
    return head + payload


def parse_client_frame(buffer: bytearray) -> tuple[int, bytes] | None:
    """(opcode, unmasked payload) of the first whole frame in ``buffer`` (removed from it), None if partial;
    ValueError on a frame a client must not send (unmasked, too large)."""
    if len(buffer) < 2:
        return None
    opcode, masked, n = buffer[0] & 0x0F, buffer[1] & 0x80, buffer[1] & 0x7F
    at = 2
    if n == 126:
        if len(buffer) < 4:
            return None
        n, at = struct.unpack(">H", buffer[2:4])[0], 4
    elif n == 127:
        if len(buffer) < 10:
            return None
        n, at = struct.unpack(">Q", buffer[2:10])[0], 10
    if not masked or n > MAX_CLIENT_FRAME:
        raise ValueError("unmasked or oversized client frame")
    if len(buffer) < at + 4 + n:
        return None
    mask = bytes(buffer[at:at + 4])
    data = bytes(buffer[at + 4:at + 4 + n])
    del buffer[:at + 4 + n]
    payload = bytes(b ^ mask[i % 4] for i, b in enumerate(data)) if n else b""
    return opcode, payload


def live_page(rig, rig_name: str = "", title: str = "hackneck live") -> str:
    """The viewer page in live mode: the rig's GLB (larynx targets over ``LIVE_TAU_RANGE``), no clip."""
    names = list(rig.joint_names) if hasattr(rig, "joint_names") else None
    tau = np.asarray(LIVE_TAU_RANGE, np.float64)
    params = AnimationParams(time=np.arange(2) / 30.0, fps=30.0, psi=np.zeros((2, rig.num_expressions)),
                             tau=tau, eta=np.ones(2), theta=np.zeros((2, rig.num_joints, 3), np.float32),
                             head_rotation=np.tile(np.eye(3), (2, 1, 1)), joint_names=names,
                             expression_names=list(rig.expression_names), rig=rig_name,
                             rig_checksum=rig_checksum(rig.rig))
    header = clip_header(params, rig, title)
    header.pop("data")
    header["frames"] = 0
    return render_page(header, glb_bytes(params, rig, "live"))


class _Client:
    def __init__(self, sock: socket.socket):
        self.sock = sock
        self.inbuf = bytearray()
        self.out = bytearray()          # bytes being written (the page, a handshake, one message)
        self.queue: deque[bytes] = deque(maxlen=CLIENT_FRAMES)
        self.ws = False
        self.closing = False            # close after ``out`` is written
        self.progress = time.monotonic()


class ViewerServer:
    """Serve ``page`` on ``host:port`` and broadcast published frames to WebSocket clients."""

    def __init__(self, page: str, host: str = "127.0.0.1", port: int = 8765, announce=print):
        self.page = page.encode("utf-8")
        self.announce = announce
        self.inbox: deque = deque(maxlen=INBOX)
        self.listener = socket.create_server((host, port), reuse_port=False)
        self.listener.setblocking(False)
        self.selector = selectors.DefaultSelector()
        self.selector.register(self.listener, selectors.EVENT_READ, None)
        self.clients: dict[socket.socket, _Client] = {}
        self.sent = self.dropped_clients = 0
        self._stop = threading.Event()
        self.thread = threading.Thread(target=self._run, name="live-viewer", daemon=True)

    @property
    def address(self) -> tuple[str, int]:
        return self.listener.getsockname()[:2]

    def start(self) -> ViewerServer:
        self.thread.start()
        return self

    def close(self, timeout: float = 2.0) -> None:
        self._stop.set()
        if self.thread.is_alive():
            self.thread.join(timeout)
        for client in list(self.clients.values()):
            self._drop(client)
        try:
            self.selector.close()
        finally:
            self.listener.close()

    # ---- the receiver's side: never blocks, never raises
    def publish(self, phone: str, fps: float, index: int, theta, psi, tau: float, eta: float) -> None:
        try:
            self.inbox.append((phone, fps, index, theta, psi, tau, eta))
        except Exception:  # noqa: BLE001 -- the live view must not disturb the receiver
            pass

    # ---- the thread
    def _run(self) -> None:
        try:
            while not self._stop.is_set():
                for key, events in self.selector.select(timeout=0.01):
                    if key.data is None:
                        self._accept()
                    else:
                        self._serve(key.data, events)
                self._broadcast()
                self._stalls()
        except Exception as error:  # noqa: BLE001 -- stop the live view, not the receiver
            if not self._stop.is_set():
                self.announce(f"live: the live view stopped: {type(error).__name__}: {error}")

    def _accept(self) -> None:
        try:
            sock, _ = self.listener.accept()
        except (BlockingIOError, InterruptedError, OSError):
            return
        if len(self.clients) >= MAX_CLIENTS:
            sock.close()
            return
        sock.setblocking(False)
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        client = self.clients[sock] = _Client(sock)
        self.selector.register(sock, selectors.EVENT_READ, client)

    def _drop(self, client: _Client) -> None:
        if self.clients.pop(client.sock, None) is not None:
            try:
                self.selector.unregister(client.sock)
            except (KeyError, ValueError, OSError):
                pass
        try:
            client.sock.close()
        except OSError:
            pass

    def _serve(self, client: _Client, events: int) -> None:
        try:
            if events & selectors.EVENT_READ:
                data = client.sock.recv(65536)
                if not data:
                    self._drop(client)
                    return
                client.inbuf += data
                self._request(client) if not client.ws else self._messages(client)
            if client.sock in self.clients and events & selectors.EVENT_WRITE:
                self._write(client)
        except (BlockingIOError, InterruptedError):
            pass
        except (OSError, ValueError):
            self._drop(client)

    def _request(self, client: _Client) -> None:
        if len(client.inbuf) > MAX_REQUEST:
            raise ValueError("request head too large")
        end = client.inbuf.find(b"\r\n\r\n")
        if end < 0:
            return
        head = client.inbuf[:end].decode("latin-1").split("\r\n")
        del client.inbuf[:end + 4]
        parts = head[0].split()
        fields = {}
        for line in head[1:]:
            name, _, value = line.partition(":")
            fields[name.strip().lower()] = value.strip()
        path = parts[1].split("?")[0] if len(parts) >= 2 else ""
        if len(parts) < 3 or parts[0] != "GET":
            self._respond(client, "405 Method Not Allowed", b"GET only\n")
        elif path == "/ws" and "websocket" in fields.get("upgrade", "").lower() and "sec-websocket-key" in fields:
            client.out += (f"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                           f"Sec-WebSocket-Accept: {accept_key(fields['sec-websocket-key'])}\r\n\r\n").encode()
            client.ws = True
            self._write(client)
            if client.inbuf:
                self._messages(client)
        elif path in ("/", "/index.html"):
            self._respond(client, "200 OK", self.page, "text/html; charset=utf-8")
        else:
            self._respond(client, "404 Not Found", b"not found\n")

    def _respond(self, client: _Client, status: str, body: bytes, kind: str = "text/plain; charset=utf-8") -> None:
        client.out += (f"HTTP/1.1 {status}\r\nContent-Type: {kind}\r\nContent-Length: {len(body)}\r\n"
                       f"Cache-Control: no-store\r\nConnection: close\r\n\r\n").encode() + body
        client.closing = True
        self._write(client)

    def _messages(self, client: _Client) -> None:
        while (message := parse_client_frame(client.inbuf)) is not None:
            opcode, payload = message
            if opcode == 0x8:                                   # close: answer it, then close
                client.queue.clear()
                client.out += ws_frame(payload[:2], 0x8)
                client.closing = True
                self._write(client)
                return
            if opcode == 0x9:                                   # ping: pong (ahead of queued frames)
                client.out += ws_frame(payload[:125], 0xA)
                self._write(client)

    def _write(self, client: _Client) -> None:
        while True:
            if not client.out and client.ws and not client.closing and client.queue:
                client.out += client.queue.popleft()
            if not client.out:
                break
            try:
                n = client.sock.send(client.out)
            except (BlockingIOError, InterruptedError):
                break
            if n <= 0:
                break
            del client.out[:n]
            client.progress = time.monotonic()
        if not client.out and client.closing:
            self._drop(client)
            return
        want = selectors.EVENT_READ | (selectors.EVENT_WRITE if client.out else 0)
        if self.selector.get_key(client.sock).events != want:
            self.selector.modify(client.sock, want, client)

    def _broadcast(self) -> None:
        if not self.inbox:
            return
        messages = []
        while self.inbox:
            phone, fps, index, theta, psi, tau, eta = self.inbox.popleft()
            text = json.dumps({"phone": phone, "time": index / fps, "frame": index,
                               "theta": np.asarray(theta, np.float64).tolist(),
                               "psi": np.asarray(psi, np.float64).tolist(), "tau": float(tau), "eta": float(eta)},
                              separators=(",", ":"))
            messages.append(ws_frame(text.encode("utf-8")))
        for client in list(self.clients.values()):
            if client.ws and not client.closing:
                if not client.out and not client.queue:
                    client.progress = time.monotonic()
                client.queue.extend(messages[-CLIENT_FRAMES:])
                try:
                    self._write(client)
                except OSError:
                    self._drop(client)
        self.sent += len(messages)

    def _stalls(self) -> None:
        now = time.monotonic()
        for client in list(self.clients.values()):
            if (client.out or client.queue) and now - client.progress > STALL_SECONDS:
                self.dropped_clients += 1
                self._drop(client)


def start_viewer(models, host: str, port: int, eta: float, announce=print) -> tuple[ViewerServer, object]:
    """Build the live page for ``models.rig``, start the server; (server, the hook for ``LiveReceiver``)."""
    server = ViewerServer(live_page(models.rig, models.rig_name), host, port, announce).start()

    def on_frame(stream, k: int) -> None:
        record = stream.recorded
        server.publish(f"{stream.device}/{stream.subject}", stream.fps, k, record.theta[k], record.psi[k],
                       record.tau[k], eta)
    return server, on_frame
