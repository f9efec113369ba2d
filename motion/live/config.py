"""The settings of ``python -m motion.live`` (``configs/live.yaml``): the :class:`LiveConfig` schema."""
from __future__ import annotations

import ipaddress
from dataclasses import dataclass

from base.cli import register_config
from motion.head2neck import UNITS


def parse_allow(allow) -> list:
    """``allow`` (an address or network, or a list of them: ``192.168.1.20``, ``10.0.0.0/24``) as
    ``ipaddress`` networks; ValueError naming the entry that is neither."""
    if allow is None:
        return []
    entries = [allow] if isinstance(allow, str) else list(allow)
    networks = []
    for entry in entries:
        try:
            networks.append(ipaddress.ip_network(str(entry).strip(), strict=False))
        except ValueError:
            raise ValueError(f"allow={entry}: expected an IP address (192.168.1.20) or a network "
                             f"(192.168.1.0/24)") from None
    return networks


@dataclass
class LiveConfig:
    """``python -m motion.live``: receive Live Link Face v6 datagrams and drive the neck and larynx."""

    host: str = "0.0.0.0"              # address to listen on (0.0.0.0: every interface)
    port: int = 11111                  # Live Link Face's default target port
    out_dir: str | None = None         # null: runs/live/<time>/; written whole when the receiver stops
    duration: float | None = None      # seconds; null = until Ctrl-C / SIGTERM
    checkpoint: str = "default"        # larynx model: default (shipped) | none (the larynx rests) | a checkpoint
    head2neck: str = "default"         # default (shipped) | none (the neck rests) | a checkpoint
    rig: str | None = None             # rig file from python -m data.assets; null = the built-in rig
    eta: float = 1.0                   # larynx size
    # Head angles as streamed (conventions: motion/head2neck/cli.py).  rad: what our sender sends (the CSV's
    # values, radians); a phone whose stream is Unreal's degrees/180 needs head_units=halfturn.
    head_units: str = "rad"            # rad | deg | halfturn
    yaw_sign: float = 1.0
    pitch_sign: float = 1.0
    roll_sign: float = 1.0
    recenter: bool = False             # the phone's first frame is the rest pose
    max_phones: int = 8                # streams kept at once (device id + subject); more are refused
    max_gap_seconds: float = 10.0      # a frame-number jump longer than this is refused ("jump"), not filled
    max_lead_seconds: float = 30.0     # a phone's clock ahead of ours (since its first frame) by more: "ahead"
    idle_seconds: float = 10.0         # a phone silent this long is closed (written) and frees its slot
    allow: list[str] | None = None     # accept only these addresses / networks ([192.168.1.20, 10.0.0.0/24])
    absurd_weight: float = 10.0        # a weight beyond +-this refuses the datagram ("absurd")
    status_seconds: float = 5.0        # a status line this often (0: none)
    tick_ms: float = 2.0               # the socket is waited on at most this long between drains
    threads: int = 1                   # torch threads (one frame at a time runs on one)
    viewer: bool = False               # serve the live view: http://viewer_host:viewer_port/ (WebSocket /ws)
    viewer_host: str = "127.0.0.1"     # the live view's address (0.0.0.0: other machines may watch)
    viewer_port: int = 8765            # 0: any free port (printed)
    # A face video instead of a phone (motion/live/face_feed.py; pip install ".[video]"):
    camera: int | None = None          # a webcam's index (0: the first); null: listen for phones
    video: str | None = None           # a video file, played at its own rate (realtime=false: as fast as it decodes)
    realtime: bool = True
    face_model: str | None = None      # a face_landmarker.task; null: the installed one
    mirror: bool = False               # selfie-mirrored frames: left/right weights swapped, yaw and roll negated

    def __post_init__(self) -> None:
        if self.head_units not in UNITS:
            raise ValueError(f"head_units={self.head_units}: expected one of {', '.join(UNITS)}")
        for name in ("yaw_sign", "pitch_sign", "roll_sign"):
            if float(getattr(self, name)) not in (1.0, -1.0):
                raise ValueError(f"{name}={getattr(self, name)}: expected +1 or -1")
        if not 0 < self.port < 65536:
            raise ValueError(f"port={self.port}: expected 1..65535")
        if not 0 <= self.viewer_port < 65536:
            raise ValueError(f"viewer_port={self.viewer_port}: expected 0..65535 (0: any free port)")
        if self.duration is not None and self.duration <= 0:
            raise ValueError(f"duration={self.duration}: expected seconds > 0 (or null: until stopped)")
        if self.camera is not None and self.video is not None:
            raise ValueError(f"camera={self.camera} and video={self.video}: give one source")
        if (self.max_phones < 1 or self.max_gap_seconds <= 0 or self.absurd_weight <= 0 or self.tick_ms <= 0
                or self.max_lead_seconds <= 0 or self.idle_seconds <= 0):
            raise ValueError("max_phones, max_gap_seconds, max_lead_seconds, idle_seconds, absurd_weight and "
                             "tick_ms must be positive")
        parse_allow(self.allow)  # ValueError naming an entry that is no address or network

    @property
    def signs(self) -> tuple[float, float, float]:
        return float(self.yaw_sign), float(self.pitch_sign), float(self.roll_sign)


register_config("live_schema", LiveConfig)
