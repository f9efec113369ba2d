"""The live view of ``python -m motion.live viewer=true``: the ``websockets`` library's threaded server.

``GET /`` returns the viewer page (``scene.viewer``, the rig's GLB embedded, no clip: the page starts in live
mode), built once and served from memory (no file is ever read for a request); ``/ws`` is a WebSocket (the
handshake, framing and protocol checks are the library's) on which every output frame is sent as a JSON text
message ``{phone, time, frame, theta [J][3], psi [E], tau, eta}``.  Anything else is 404.

Who may talk to it (the page's own origin only, against cross-site WebSocket hijacking and DNS rebinding):
the ``Host`` of every request must be this server's own name with its port (``localhost``, ``127.0.0.1``,
``[::1]`` or ``viewer_host``; with a wildcard ``viewer_host`` such as 0.0.0.0, any IP address literal, which
DNS rebinding cannot produce), and an ``Origin``, where the request has one, must be ``http://`` + that Host
(also given to the library as ``origins=``); otherwise 403.  A request without ``Origin`` is not a browser's
(browsers always send it on WebSocket handshakes), and a program on the machine can write any Origin anyway.

Bounds (per connection, whatever the peer does): at most ``MAX_CONNECTIONS`` at once, handshaking or open (more
are closed at once); ``OPEN_TIMEOUT`` to send a whole request; ``SEND_TIMEOUT`` for any send (the page, a
frame, a pong): a client that stalls is dropped; reads throttled to ``READ_RATE`` bytes/s (a browser sends only
pongs and a close), messages from a client at most ``MAX_MESSAGE`` bytes and ``MAX_QUEUE`` of them held (the
library stops reading beyond), keepalive pings every ``PING_SECONDS``.  The request head is bounded by the
library (8 KiB lines, 128 headers) and a pipelined second request is discarded.

The receiver only calls :meth:`ViewerServer.publish` (append to a bounded deque and set an event: never blocks
on a client, never raises); a broadcaster thread encodes each frame once and leaves it in every client's
bounded queue (the latest ``CLIENT_FRAMES`` kept); each client's own thread (the library's) sends.  Anything
going wrong in the broadcaster stops the live view (announced), never the receiver.
"""
from __future__ import annotations

import ipaddress
import json
import logging
import re
import socket
import threading
import time
from collections import deque
from http import HTTPStatus

import numpy as np
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response
from websockets.protocol import OPEN
from websockets.sync.server import ServerConnection, serve

from data.params import AnimationParams, rig_checksum
from scene.viewer.build import clip_header, glb_bytes, render_page

INBOX = 256               # frames waiting for the broadcaster (all phones); older ones are dropped
CLIENT_FRAMES = 8         # messages queued per browser; older ones are dropped (the latest kept)
MAX_CONNECTIONS = 32      # connections at once (handshaking or open); a stalled one frees its slot by the timeouts
OPEN_TIMEOUT = 5.0        # seconds to send a whole request (a connection that sends nothing is closed)
SEND_TIMEOUT = 10.0       # seconds any one send may take (the page, a frame): a client that stalls is dropped
PING_SECONDS = 10.0       # keepalive ping interval, and the time its pong may take
CLOSE_TIMEOUT = 2.0       # seconds for a client to answer our close
MAX_MESSAGE = 4096        # bytes of a message from a browser (it sends none but pongs and a close)
MAX_QUEUE = 4             # messages from a browser held unread; the library stops reading beyond
READ_RATE = 16384         # bytes/s read from one connection (a token bucket of one second)
LOOPBACK = ("localhost", "127.0.0.1", "::1")
WILDCARD = ("0.0.0.0", "::", "")
LIVE_TAU_RANGE = (-0.1, 0.1)  # the larynx targets of the live GLB span this tau range (clamped beyond)
OUR_FAILURES = ("process_request failed", "connection handler failed")  # the library's words for our bugs


class _PeerErrors(logging.Filter):
    """Counts, instead of printing, the library's errors a peer can cause at will (e.g. a request followed by
    more bytes before its answer: "unexpected internal error" with a traceback); our own hooks' failures pass."""

    def __init__(self):
        super().__init__()
        self.count = 0

    def filter(self, record: logging.LogRecord) -> bool:
        if record.levelno >= logging.WARNING and record.msg not in OUR_FAILURES:
            self.count += 1
            return False
        return True


LOG = logging.getLogger("motion.live.viewer")
PEER_ERRORS = _PeerErrors()
LOG.addFilter(PEER_ERRORS)


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


def authority(host: str, port: int) -> str:
    """``host:port`` as a browser writes it in ``Host`` (IPv6 in brackets, lower case)."""
    host = host.strip("[]").lower()
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


def own_hosts(viewer_host: str, port: int) -> set[str]:
    """The ``Host`` values naming this server: the loopback names and ``viewer_host``, with ``port``."""
    return {authority(name, port) for name in (*LOOPBACK, viewer_host) if name not in WILDCARD}


def is_ip_authority(value: str, port: int) -> bool:
    """Whether ``value`` is an IP address literal with ``port`` (what a wildcard-bound server accepts)."""
    host, sep, number = value.rpartition(":")
    if not sep or number != str(port):
        return False
    try:
        ipaddress.ip_address(host[1:-1] if host.startswith("[") and host.endswith("]") else host)
    except ValueError:
        return False
    return ":" not in host or host.startswith("[")


class _ThrottledSocket(socket.socket):
    """A connected socket whose ``recv`` takes at most ``READ_RATE`` bytes a second (token bucket of one second):
    a client flooding frames costs the process at most that much parsing."""

    def __init__(self, sock: socket.socket):
        super().__init__(sock.family, sock.type, sock.proto, fileno=sock.detach())
        self.tokens, self.at = float(READ_RATE), time.monotonic()

    def recv(self, size: int, flags: int = 0) -> bytes:
        now = time.monotonic()
        self.tokens, self.at = min(float(READ_RATE), self.tokens + (now - self.at) * READ_RATE), now
        if self.tokens < 512:
            time.sleep((512 - self.tokens) / READ_RATE)
            self.tokens, self.at = 512.0, time.monotonic()
        data = super().recv(min(size, int(self.tokens)), flags)
        self.tokens -= len(data)
        return data


class _Connection(ServerConnection):
    """The library's connection with its slot released when its socket closes, and its outgoing queue."""

    def __init__(self, sock, protocol, server, release, **kwargs):
        self.outbox: deque[str] = deque(maxlen=CLIENT_FRAMES)
        self.ready = threading.Event()
        self._release, self._release_lock = release, threading.Lock()
        super().__init__(sock, protocol, server, **kwargs)

    def close_socket(self) -> None:
        super().close_socket()
        self.ready.set()
        with self._release_lock:
            release, self._release = self._release, None
        if release is not None:
            release(self)

    def abort(self) -> None:
        """Wake any send or read of this connection (server stopping): they fail and the thread ends."""
        try:
            self.socket.shutdown(socket.SHUT_RDWR)
        except OSError:
            pass


class ViewerServer:
    """Serve ``page`` on ``host:port`` and broadcast published frames to WebSocket clients."""

    def __init__(self, page: str, host: str = "127.0.0.1", port: int = 8765, announce=print):
        self.page = page.encode("utf-8")
        self.announce = announce
        self.inbox: deque = deque(maxlen=INBOX)
        self.sent = self.dropped_clients = self.refused_connections = 0   # dropped: for stalling (SEND_TIMEOUT)
        self.clients: set[_Connection] = set()        # open WebSockets, fed by the broadcaster
        self.connections: set[_Connection] = set()    # every connection holding a slot
        self._lock = threading.Lock()
        self._slots = threading.BoundedSemaphore(MAX_CONNECTIONS)
        self._wake, self._stop = threading.Event(), threading.Event()
        listener = socket.create_server((host, port), family=socket.AF_INET6 if ":" in host else socket.AF_INET)
        self.port = listener.getsockname()[1]
        self.hosts = own_hosts(host, self.port)
        self.any_ip = host in WILDCARD
        origins = [None, *sorted(f"http://{h}" for h in self.hosts)]
        if self.any_ip:
            origins.append(re.compile(rf"http://[0-9a-fA-F.:\[\]]+:{self.port}"))
        self.server = serve(self._handler, sock=listener, origins=origins, process_request=self._process_request,
                            compression=None, open_timeout=OPEN_TIMEOUT, ping_interval=PING_SECONDS,
                            ping_timeout=PING_SECONDS, close_timeout=CLOSE_TIMEOUT, max_size=MAX_MESSAGE,
                            max_queue=MAX_QUEUE, server_header=None, create_connection=self._connection,
                            logger=LOG)
        self.thread = threading.Thread(target=self.server.serve_forever, name="live-viewer", daemon=True)
        self.broadcaster = threading.Thread(target=self._broadcast, name="live-viewer-broadcast", daemon=True)

    @property
    def address(self) -> tuple[str, int]:
        return self.server.socket.getsockname()[:2]

    def start(self) -> ViewerServer:
        self.thread.start()
        self.broadcaster.start()
        return self

    def close(self, timeout: float = 2.0) -> None:
        self._stop.set()
        self._wake.set()
        with self._lock:
            connections = list(self.connections)
        for connection in connections:
            connection.ready.set()
            connection.abort()
        self.server.shutdown()
        self.thread.join(timeout)
        self.broadcaster.join(timeout)

    # ---- the receiver's side: never blocks on a client, never raises
    def publish(self, phone: str, fps: float, index: int, theta, psi, tau: float, eta: float) -> None:
        try:
            self.inbox.append((phone, fps, index, theta, psi, tau, eta))
            self._wake.set()
        except Exception:  # noqa: BLE001 -- the live view must not disturb the receiver
            pass

    # ---- the library's hooks (each connection's own thread)
    def _connection(self, sock, protocol, server, **kwargs) -> _Connection:
        """A connection, if a slot is free (else the library closes the socket); reads throttled, sends timed."""
        if not self._slots.acquire(blocking=False):
            with self._lock:
                self.refused_connections += 1
            raise ConnectionRefusedError("live view: too many connections")
        throttled = None
        try:
            throttled = _ThrottledSocket(sock)
            throttled.settimeout(SEND_TIMEOUT)     # every sendall (the library's) fails past it
            connection = _Connection(throttled, protocol, server, self._release, **kwargs)
        except BaseException:
            if throttled is not None:
                throttled.close()
            self._slots.release()
            raise
        with self._lock:
            self.connections.add(connection)
        return connection

    def _release(self, connection: _Connection) -> None:
        with self._lock:
            self.connections.discard(connection)
            self.clients.discard(connection)
            # a send (a frame, a ping, the page) that took SEND_TIMEOUT, by any of its threads: stalled, dropped
            if isinstance(connection.connection_exc, TimeoutError) and not self._stop.is_set():
                self.dropped_clients += 1
        self._slots.release()

    def _process_request(self, connection: ServerConnection, request: Request) -> Response | None:
        """403 unless Host (and Origin, where given) are this page's own; the page; 404; None: the WebSocket."""
        hosts = request.headers.get_all("Host")
        host = hosts[0].strip().lower() if len(hosts) == 1 else None
        if host is None or not (host in self.hosts or (self.any_ip and is_ip_authority(host, self.port))):
            return connection.respond(HTTPStatus.FORBIDDEN, "Host is not this live view's\n")
        origins = request.headers.get_all("Origin")
        if origins and origins != [f"http://{host}"]:
            return connection.respond(HTTPStatus.FORBIDDEN, "Origin is not this live view's\n")
        path = request.path.split("?")[0]
        if path == "/ws":
            return None                     # the library checks the handshake, Origin (origins=) and version
        if path not in ("/", "/index.html"):
            return connection.respond(HTTPStatus.NOT_FOUND, "not found\n")
        if request.method != "GET" or request.headers.get_all("Upgrade"):
            return connection.respond(HTTPStatus.METHOD_NOT_ALLOWED, "GET only\n")
        headers = Headers([("Content-Type", "text/html; charset=utf-8"), ("Content-Length", str(len(self.page))),
                           ("Cache-Control", "no-store"), ("X-Content-Type-Options", "nosniff"),
                           ("X-Frame-Options", "DENY"), ("Referrer-Policy", "no-referrer"),
                           ("Connection", "close")])
        return Response(HTTPStatus.OK.value, HTTPStatus.OK.phrase, headers, self.page)

    def _handler(self, connection: _Connection) -> None:
        """Send this client its queued frames until it closes, stalls (SEND_TIMEOUT) or the server stops."""
        with self._lock:
            self.clients.add(connection)
        try:
            while not self._stop.is_set():
                connection.ready.wait(0.5)          # set by the broadcaster, and when the socket closes
                connection.ready.clear()
                if connection.protocol.state is not OPEN:
                    return
                while connection.outbox:
                    connection.send(connection.outbox.popleft())
        except ConnectionClosed:
            pass                                    # closed by the client, a stall (counted on release), stop
        finally:
            with self._lock:
                self.clients.discard(connection)

    # ---- the broadcaster: encodes each frame once, never touches a socket
    def _broadcast(self) -> None:
        try:
            while not self._stop.is_set():
                if not self._wake.wait(0.5):
                    continue
                self._wake.clear()
                messages = []
                while self.inbox:
                    phone, fps, index, theta, psi, tau, eta = self.inbox.popleft()
                    messages.append(json.dumps({"phone": phone, "time": index / fps, "frame": index,
                                                "theta": np.asarray(theta, np.float64).tolist(),
                                                "psi": np.asarray(psi, np.float64).tolist(), "tau": float(tau),
                                                "eta": float(eta)}, separators=(",", ":")))
                with self._lock:
                    clients = list(self.clients)
                for client in clients:
                    client.outbox.extend(messages[-CLIENT_FRAMES:])
                    client.ready.set()
                self.sent += len(messages)
        except Exception as error:  # noqa: BLE001 -- stop the live view, not the receiver
            if not self._stop.is_set():
                self.announce(f"live: the live view stopped: {type(error).__name__}: {error}")


def start_viewer(models, host: str, port: int, eta: float, announce=print) -> tuple[ViewerServer, object]:
    """Build the live page for ``models.rig``, start the server; (server, the hook for ``LiveReceiver``)."""
    server = ViewerServer(live_page(models.rig, models.rig_name), host, port, announce).start()

    def on_frame(stream, k: int) -> None:
        record = stream.recorded
        server.publish(f"{stream.device}/{stream.subject}", stream.fps, k, record.theta[k], record.psi[k],
                       record.tau[k], eta)
    return server, on_frame
