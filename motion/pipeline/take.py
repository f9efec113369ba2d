"""One take end to end: read and animate it, retarget it onto the character, and write its folder whole
or not at all."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from base.files import atomic_folder
from data.params import save_params
from motion.pipeline.animate import animate, read_take
from motion.pipeline.config import InferConfig
from motion.pipeline.models import Models
from motion.pipeline.outputs import write_outputs
from motion.retarget import default_gains, retarget_params
from scene.characters import GIRAFFE_TAG


def run_take(cfg: InferConfig, models: Models, path: str | None, out_dir: Path, announce=print) -> dict:
    """Read, animate and write one take into ``out_dir`` (whole or not at all); a summary row."""
    started = time.perf_counter()
    track = read_take(cfg, path)
    read_seconds = time.perf_counter() - started
    if track.missing:
        announce(f"{track.source}: no column for {', '.join(track.missing)} (left at 0)")
    params, seconds = animate(cfg, models, track, announce)
    with atomic_folder(out_dir) as staging:
        if models.character is not None:
            started = time.perf_counter()
            save_params(staging / "source_params.npz", params)
            label = str(cfg.character)
            if cfg.character == GIRAFFE_TAG:  # built on the fly: the file beside the params names it
                models.character.rig.save(staging / "character.npz")
                label = str((out_dir / "character.npz").resolve())
            params = retarget_params(params, models.rig, models.character, label, default_gains(models.character),
                                     source_name=str(track.source))
            seconds["retarget"] = time.perf_counter() - started
        seconds.update(write_outputs(cfg, models, params, staging, announce))
    seconds = {"read": read_seconds, **seconds}
    return {"take": str(track.source), "status": "ok", "frames": len(params), "fps": params.fps,
            "seconds": round(float(params.time[-1]), 3), "tau_range": float(np.ptp(params.tau)),
            "max_joint_deg": float(np.degrees(np.linalg.norm(params.theta, axis=-1)).max()),
            "out": str(out_dir), "stage_seconds": seconds, "reason": ""}
