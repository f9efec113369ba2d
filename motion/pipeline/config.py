"""The settings of ``python infer.py`` (``configs/infer.yaml``): the :class:`InferConfig` schema."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from base.cli import register_config
from motion.swallow import PlaybackConfig
from scene.fbx import FBX_UNITS
from scene.usd import USD_FORMATS, USD_UNITS

MESH_FORMATS = ("ply", "obj")
EXPORTS = ("glb", "mp4", "html", "fbx", "usd")


@dataclass
class InferConfig:
    """``python infer.py``: settings (see infer.py's docstring)."""

    expressions: str | None = None  # a recording (.csv/.npy), a folder of them, or null for the demo take
    out_dir: str | None = None      # null: runs/infer/<time>/
    fps: float | None = None        # frame rate of header-less or .npy expressions (others carry their own)
    timecode_fps: float | None = None  # Live Link Face timecode rate, needed for takes under a second
    out_fps: float | None = None    # output rate without a larynx model; null = the recording's
    allow_missing: bool = False        # run a capture that lacks some ARKit expression columns (left at 0)
    # expressions -> tau
    checkpoint: str = "default"        # larynx model: default (shipped) | none (the larynx rests) | a checkpoint
    subject: str | None = None         # a training subject's style; null = the average style
    eta: float = 1.0                   # larynx size
    # swallows
    swallow_template: str = "default"  # default (shipped) | a template CSV from python -m motion.swallow
    swallow_at: list[float] = field(default_factory=list)  # onset times (s); the demo take swallows at 6.2 s
    swallow_duration_scale: Any = 1.0  # one value or one per onset
    swallow_amplitude_scale: Any = 1.0
    swallow_playback: PlaybackConfig = field(default_factory=PlaybackConfig)
    # head rotation -> cervical theta (conventions in motion/head2neck/__init__.py)
    head2neck: str = "default"         # default (shipped) | none (the neck rests) | a checkpoint
    head_units: str = "rad"            # rad | deg | halfturn
    yaw_sign: float = 1.0
    pitch_sign: float = 1.0
    roll_sign: float = 1.0
    recenter: bool = False
    # face video (expressions=clip.mp4; motion/face/__init__.py): MediaPipe FaceLandmarker
    face_model: str | None = None      # a face_landmarker.task; null: the installed one (pip install ".[video]")
    mirror: bool = False               # selfie-mirrored footage: left/right weights swapped, yaw and roll negated
    face_smoothing: bool = False       # causal One Euro filter on weights and pose (benchmarks/README.md, Face video)
    face_max_gap: float = 0.5          # s: a face lost for longer is reported (shorter gaps silently interpolated)
    # voice -> larynx height (motion.voice; docs/voice.md)
    audio: str | None = None           # null: the audio beside the take (same stem: .wav/.mov/.mp4...) if any |
    #                                    none: no voice term | a file (one take)
    voice: str = "default"             # default (published figures) | a voice.json from python -m motion.voice
    audio_tolerance: float = 1.0       # s: audio and capture durations may differ by this much (aligned at start)
    # rig and outputs
    rig: str | None = None             # rig file from python -m data.assets; null = the built-in rig
    character: str = "human"           # human | giraffe (built from the rig) | a character file (.npz)
    meshes: bool = False               # one mesh per frame in meshes/
    mesh_format: str = "ply"           # ply | obj
    export: list[str] = field(default_factory=list)  # glb, mp4, html (viewer.html), fbx (anim.fbx, needs Blender),
    #                                    usd (anim.usdc, UsdSkel: scene.usd)
    fbx_units: str = "cm"              # cm (Unreal, Maya) | m
    usd_format: str = "usdc"           # usdc | usda (text) | usdz (Apple's Quick Look): anim.<usd_format>
    usd_units: str = "cm"              # cm (metersPerUnit 0.01) | m
    plot: bool = True
    workers: int = 1                   # takes of a folder run in this many processes
    threads: int = 1                   # torch threads per process (per-frame decoding runs on one)

    def __post_init__(self) -> None:
        if not self.audio_tolerance >= 0:
            raise ValueError(f"audio_tolerance={self.audio_tolerance}: expected seconds >= 0")
        if self.mesh_format not in MESH_FORMATS:
            raise ValueError(f"mesh_format={self.mesh_format}: expected one of {', '.join(MESH_FORMATS)}")
        if self.fbx_units not in FBX_UNITS:
            raise ValueError(f"fbx_units={self.fbx_units}: expected one of {', '.join(FBX_UNITS)}")
        if self.usd_format not in USD_FORMATS:
            raise ValueError(f"usd_format={self.usd_format}: expected one of {', '.join(USD_FORMATS)}")
        if self.usd_units not in USD_UNITS:
            raise ValueError(f"usd_units={self.usd_units}: expected one of {', '.join(USD_UNITS)}")
        unknown = [e for e in self.export if e not in EXPORTS]
        if unknown:
            raise ValueError(f"export={unknown}: expected some of {', '.join(EXPORTS)}")
        if self.workers < 1:
            raise ValueError(f"workers={self.workers}: expected at least 1")
        if self.swallow_template != "default" and not self.swallow_at:
            raise ValueError(f"swallow_template={self.swallow_template} needs swallow_at=[t1,...] (seconds)")


register_config("infer_schema", InferConfig)
