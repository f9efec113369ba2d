"""The sender's settings (:class:`LiveSendConfig`, ``configs/live_send.yaml``) and its loop: one datagram
per row, paced by the take's own timecode."""
from __future__ import annotations

import socket
import time
from dataclasses import dataclass

from base.cli import REQUIRED, register_config, to_dataclass
from base.errors import InputError
from motion.live.packet import encode
from motion.live.send.take import Take, read_take


@dataclass
class LiveSendConfig:
    """``python -m motion.live.send``: a Live Link Face CSV replayed as v6 datagrams (see the package docstring)."""

    take: str = REQUIRED               # a Live Link Face CSV, or demo (the built-in demo take)
    host: str = "127.0.0.1"
    port: int = 11111
    speed: float = 1.0                 # 2: twice as fast; 0: as fast as possible
    subject: str = "take"              # the subject name sent (Live Link Face: the phone's subject)
    device: str = "00000000-0000-4000-8000-00000000a11e"  # the device id sent (a UUID)
    timecode_fps: int | None = None    # the CSV's timecode rate; null: guessed from the frames seen
    loops: int = 1                     # play the take this many times (frame numbers keep increasing)

    def __post_init__(self) -> None:
        if self.speed < 0:
            raise ValueError(f"speed={self.speed}: expected >= 0 (0: as fast as possible)")
        if self.loops < 1:
            raise ValueError(f"loops={self.loops}: expected at least 1")


register_config("live_send_schema", LiveSendConfig)


def send_take(take: Take, sock: socket.socket, address: tuple[str, int], speed: float = 1.0, subject: str = "take",
              device: str = LiveSendConfig.device, loops: int = 1) -> int:
    """Send every row of ``take`` to ``address`` at its timecode's pace / ``speed``; the datagrams sent."""
    sent, start, offset = 0, time.perf_counter(), 0
    first = int(take.frames[0])
    span = int(take.frames[-1]) - first + 1
    for _ in range(loops):
        for frame, subframe, values in zip(take.frames, take.subframes, take.values):
            number = int(frame) + offset
            if speed > 0:
                delay = start + (number - first) / take.rate / speed - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            sock.sendto(encode(device, subject, number, values, float(subframe), (take.rate, 1)), address)
            sent += 1
        offset += span
    return sent


def run(cfg) -> int:
    config: LiveSendConfig = to_dataclass(cfg, LiveSendConfig, where="configs/live_send.yaml")
    take = read_take(config.take, config.timecode_fps)
    try:
        address = (socket.gethostbyname(config.host), config.port)
    except OSError as e:
        raise InputError(f"host={config.host}: cannot resolve ({e})") from None
    seconds = len(take.frames) / take.rate / (config.speed or float("inf"))
    print(f"send: {len(take.frames)} frames at {take.rate} fps to {address[0]}:{address[1]} as subject "
          f"'{config.subject}' ({seconds:.1f} s per loop, {config.loops} loop(s))")
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sent = send_take(take, sock, address, config.speed, config.subject, config.device, config.loops)
    print(f"send: {sent} datagrams sent")
    return sent
