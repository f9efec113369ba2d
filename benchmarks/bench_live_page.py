"""The live page under attack, over loopback: what a client flooding its WebSocket costs the receiver.

    python benchmarks/bench_live_page.py [--rounds 2] [--datagrams 240] [--floods ping big] [--before 5ee4caf]
                                         [--no-pin]

One phone (the demo take as Live Link Face v6 datagrams, paced at 60 fps, sent from this process), the
receiver (``LiveReceiver``, shipped models, one torch thread) and the live page server
(``motion.live.viewer_server``) in this process, one well-behaved page reading the WebSocket.  Per run, the
receive -> params latency of the output frames p50 / p99 (ms), the broadcast latency (params -> the reading
page has the frame) p50 / p99 (ms), and this process's CPU use (% of a core), quiet and while another process
floods: ``ping`` (125-byte masked pings as fast as the server reads them, pongs read) or ``big`` (64 KiB
masked binary frames, reconnecting whenever the server closes).  ``--before COMMIT``: the same with the
server of that commit (loaded from git), alternated round by round with the current one.  The flooder is
pinned to the other CPUs (``--no-pin``: it shares this one), as an attacker is another machine or process.
"""
from __future__ import annotations

import argparse
import base64
import hashlib
import importlib.util
import json
import os
import socket
import struct
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from motion.live import viewer_server  # noqa: E402
from motion.live.cli import live_models, stream_options  # noqa: E402
from motion.live.config import LiveConfig  # noqa: E402
from motion.live.packet import encode  # noqa: E402
from motion.live.receiver import LiveReceiver  # noqa: E402
from motion.live.send.take import demo_as_take  # noqa: E402

FLOODER = r"""
import base64, os, socket, sys, threading
host, port, kind = sys.argv[1], int(sys.argv[2]), sys.argv[3]
mask = os.urandom(4)
def masked(opcode, payload):
    n = len(payload)
    head = bytes([0x80 | opcode]) + (bytes([0x80 | n]) if n < 126 else bytes([0x80 | 127]) + n.to_bytes(8, "big"))
    return head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
frames = masked(0x9, bytes(125)) * 64 if kind == "ping" else masked(0x2, os.urandom(65536))
def connect():
    sock = socket.create_connection((host, port))
    sock.sendall((f"GET /ws HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                  f"Sec-WebSocket-Key: {base64.b64encode(os.urandom(16)).decode()}\r\n"
                  f"Sec-WebSocket-Version: 13\r\n\r\n").encode())
    threading.Thread(target=drain, args=(sock,), daemon=True).start()
    return sock
def drain(sock):
    try:
        while sock.recv(65536):
            pass
    except OSError:
        pass
sock = connect()
print("flooding", flush=True)
while True:
    try:
        sock.sendall(frames)
    except OSError:
        sock.close()
        sock = connect()
"""


def load_server(commit: str | None):
    """The viewer_server module of ``commit`` (from git), or the current one."""
    if commit is None:
        return viewer_server
    source = subprocess.run(["git", "show", f"{commit}:motion/live/viewer_server.py"], cwd=REPO, check=True,
                            capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / f"viewer_server_{commit}.py"
    path.write_text(source)
    spec = importlib.util.spec_from_file_location(f"viewer_server_{commit}", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def read_exact(sock: socket.socket, n: int) -> bytes:
    out = b""
    while len(out) < n:
        chunk = sock.recv(n - len(out))
        if not chunk:
            raise ConnectionError("closed")
        out += chunk
    return out


def page_client(address) -> socket.socket:
    sock = socket.create_connection(address, timeout=5)
    key = base64.b64encode(os.urandom(16)).decode()
    sock.sendall((f"GET /ws HTTP/1.1\r\nHost: {address[0]}:{address[1]}\r\nOrigin: http://{address[0]}:"
                  f"{address[1]}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: {key}\r\n"
                  f"Sec-WebSocket-Version: 13\r\n\r\n").encode())
    head = b""
    while b"\r\n\r\n" not in head:
        head += read_exact(sock, 1)
    accept = base64.b64encode(hashlib.sha1(key.encode() + b"258EAFA5-E914-47DA-95CA-C5AB0DC85B11").digest())
    assert head.startswith(b"HTTP/1.1 101") and accept in head, head
    return sock


def read_frames(sock: socket.socket, arrived: dict, stop: threading.Event) -> None:
    sock.settimeout(0.5)
    while not stop.is_set():
        try:
            b0, b1 = read_exact(sock, 2)
        except TimeoutError:
            continue
        except OSError:
            return
        n = b1 & 0x7F
        if n == 126:
            n = struct.unpack(">H", read_exact(sock, 2))[0]
        elif n == 127:
            n = struct.unpack(">Q", read_exact(sock, 8))[0]
        payload = read_exact(sock, n)
        if b0 & 0x0F == 0x1:
            frame = json.loads(payload)["frame"]
            arrived[frame] = time.perf_counter()


def run(module, models, options, take, start: int, count: int, flood: str | None, flooder_cpus) -> dict:
    server, on_frame = module.start_viewer(models, "127.0.0.1", 0, 1.0, announce=lambda *_: None)
    published, arrived, stop = {}, {}, threading.Event()

    def hook(stream, k):
        published[k] = time.perf_counter()
        on_frame(stream, k)
    rx = LiveReceiver(models, options, "127.0.0.1", 0, announce=lambda *_: None, on_frame=hook)
    client = page_client(server.address)
    reader = threading.Thread(target=read_frames, args=(client, arrived, stop))
    reader.start()
    flooder = None
    if flood:
        flooder = subprocess.Popen([sys.executable, "-c", FLOODER, *map(str, server.address), flood],
                                   stdout=subprocess.PIPE, text=True,
                                   preexec_fn=(lambda: os.sched_setaffinity(0, flooder_cpus)) if flooder_cpus else None)
        assert flooder.stdout.readline().strip() == "flooding"
        time.sleep(0.5)
    try:
        cpu, wall = time.process_time(), time.perf_counter()
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            due = time.perf_counter()
            for i in range(start, start + count):
                due += 1 / 60
                time.sleep(max(0.0, due - time.perf_counter()))
                tx.sendto(encode("bench-device", "ana", take.frames[i], take.values[i]), rx.address)
                while not rx.wait(0.002):
                    pass
                rx.drain()
        time.sleep(0.2)
        cpu_share = (time.process_time() - cpu) / (time.perf_counter() - wall)
    finally:
        stop.set()
        if flooder is not None:
            flooder.kill()
            flooder.wait()
        reader.join()
        client.close()
        rx.close()
        server.close()
    stream = rx.streams[("bench-device", "ana")]
    latency = np.asarray(stream.recorded.latency_ms)
    broadcast = np.asarray([1e3 * (arrived[k] - t) for k, t in published.items() if k in arrived])
    return {"frames": len(latency), "received": len(broadcast),
            "p50": np.percentile(latency, 50), "p99": np.percentile(latency, 99),
            "b50": np.percentile(broadcast, 50) if len(broadcast) else np.nan,
            "b99": np.percentile(broadcast, 99) if len(broadcast) else np.nan, "cpu": 100 * cpu_share}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--datagrams", type=int, default=240)
    parser.add_argument("--floods", nargs="+", default=["ping", "big"])
    parser.add_argument("--before", default=None, help="a commit whose viewer_server to compare with")
    parser.add_argument("--no-pin", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    cpus = sorted(os.sched_getaffinity(0))
    flooder_cpus = None
    if not args.no_pin and len(cpus) > 1:
        os.sched_setaffinity(0, {cpus[0]})
        flooder_cpus = set(cpus[1:])
    config = LiveConfig()
    models = live_models(config, announce=lambda *_: None)
    take = demo_as_take()
    servers = [("current", load_server(None))]
    if args.before:
        servers.insert(0, (args.before, load_server(args.before)))
    print(f"{args.datagrams} datagrams at 60 fps per run, pinned: {flooder_cpus is not None}")
    print(f"{'server':>10} {'flood':>6} {'frames':>6} {'page':>5} {'p50 ms':>7} {'p99 ms':>7} {'bcast p50':>9} "
          f"{'bcast p99':>9} {'CPU %':>6} {'load':>5}")
    for _ in range(args.rounds):
        for name, module in servers:
            for flood in [None, *args.floods]:
                r = run(module, models, stream_options(config), take, 0, args.datagrams, flood, flooder_cpus)
                print(f"{name:>10} {flood or '-':>6} {r['frames']:>6} {r['received']:>5} {r['p50']:7.2f} "
                      f"{r['p99']:7.2f} {r['b50']:9.2f} {r['b99']:9.2f} {r['cpu']:6.1f} {os.getloadavg()[0]:5.2f}",
                      flush=True)


if __name__ == "__main__":
    main()
