"""One take end to end: read and animate it, retarget it onto the character, and write its folder whole
or not at all."""
from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from base.errors import InputError
from data.params import save_params
from motion.pipeline.animate import animate, read_take
from motion.pipeline.config import InferConfig
from motion.pipeline.models import Models
from motion.pipeline.outputs import write_outputs
from motion.retarget import default_gains, retarget_params
from scene.characters import GIRAFFE_TAG


def require_new_folder(out_dir: Path) -> None:
    """InputError unless ``out_dir`` is absent or an empty folder."""
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise InputError(f"out_dir={out_dir}: already exists and is not an empty folder; give a new one")


@contextlib.contextmanager
def staged_folder(out_dir: Path) -> Iterator[Path]:
    """A staging folder beside ``out_dir`` (absent or empty), renamed to it with a normal folder's mode when
    the block succeeds and removed otherwise: ``base.files.atomic_path`` for a folder."""
    require_new_folder(out_dir)
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))
    try:
        yield staging
        if out_dir.is_dir():
            out_dir.rmdir()  # empty (checked above)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(staging, 0o777 & ~umask)  # mkdtemp makes 0700
        os.replace(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging)


def run_take(cfg: InferConfig, models: Models, path: str | None, out_dir: Path, announce=print) -> dict:
    """Read, animate and write one take into ``out_dir`` (whole or not at all); a summary row."""
    started = time.perf_counter()
    track = read_take(cfg, path)
    read_seconds = time.perf_counter() - started
    if track.missing:
        announce(f"{track.source}: no column for {', '.join(track.missing)} (left at 0)")
    params, seconds = animate(cfg, models, track, announce)
    with staged_folder(out_dir) as staging:
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
