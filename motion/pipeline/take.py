"""One take end to end: read and animate it (with its audio when there is one), retarget it onto the
character, and write its folder whole or not at all."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from base.errors import InputError
from base.files import atomic_folder
from base.stopwatch import StageSeconds
from data.audio import find_audio_beside
from data.params import save_params
from motion.face import FACE_FRAMES_FILE, write_face_frames
from motion.pipeline.animate import animate, read_take
from motion.pipeline.config import InferConfig
from motion.pipeline.models import Models
from motion.pipeline.outputs import write_outputs
from motion.retarget import default_gains, retarget_params
from scene.characters import GIRAFFE_TAG


def take_audio(cfg: InferConfig, path: str | None, in_folder: bool = False) -> str | None:
    """The audio of the take at ``path``: ``audio=none`` none; ``audio=<file>`` that file (one take only);
    unset: the file beside the take with its stem (``take.wav``, ``take.mov``, ...; a video take's own
    sound), or none."""
    if cfg.audio is not None and str(cfg.audio).lower() == "none":
        return None
    if cfg.audio is not None:
        if in_folder:
            raise InputError(f"audio={cfg.audio}: one file for a folder of takes; leave audio unset (each take's "
                             f"audio is the file beside it with the same name) or give audio=none")
        return str(cfg.audio)
    found = None if path is None else find_audio_beside(path)
    return None if found is None else str(found)


def run_take(cfg: InferConfig, models: Models, path: str | None, out_dir: Path, announce=print) -> dict:
    """Read, animate and write one take into ``out_dir`` (whole or not at all); a summary row."""
    seconds = StageSeconds()
    with seconds.time("read"):
        track = read_take(cfg, path, announce)
    if track.missing:
        announce(f"{track.source}: no column for {', '.join(track.missing)} (left at 0)")
    audio = take_audio(cfg, path)
    if audio is not None and cfg.audio is None:
        announce(f"{track.source}: audio {audio} (the file beside the take; audio=none ignores it)")
    params = animate(cfg, models, track, announce, audio=audio, seconds=seconds)
    source_params = None
    with atomic_folder(out_dir, announce) as staging:
        if track.tracked is not None:  # a face video: the frames with and without a face
            write_face_frames(staging / FACE_FRAMES_FILE, track)
        if models.character is not None:
            with seconds.time("retarget"):
                source_params = params
                save_params(staging / "source_params.npz", source_params)
                label = str(cfg.character)
                if cfg.character == GIRAFFE_TAG:  # built on the fly: the file beside the params names it
                    models.character.rig.save(staging / "character.npz")
                    label = str((out_dir / "character.npz").resolve())
                params = retarget_params(source_params, models.rig, models.character, label,
                                         default_gains(models.character), source_name=str(track.source))
        write_outputs(cfg, models, params, staging, announce, out_dir, source_params, seconds)
    return {"take": str(track.source), "status": "ok", "frames": len(params), "fps": params.fps,
            "seconds": round(float(params.time[-1]), 3), "tau_range": float(np.ptp(params.tau)),
            "max_joint_deg": float(np.degrees(np.linalg.norm(params.theta, axis=-1)).max()),
            "out": str(out_dir), "stage_seconds": dict(seconds), "reason": ""}
