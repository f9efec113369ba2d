"""``python infer.py``: one take (or the demo take) or a folder of takes into ``out_dir``."""
from __future__ import annotations

import json
from datetime import datetime
from pathlib import Path

from base.cli import to_dataclass
from base.errors import InputError
from motion.pipeline.config import InferConfig
from motion.pipeline.folder import print_summary, run_folder
from motion.pipeline.models import load_models
from motion.pipeline.take import run_take
from scene.fbx import blender_executable
from scene.usd import require_usd


def default_out_dir() -> Path:
    return Path("runs") / "infer" / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def run(cfg) -> list[dict]:
    config: InferConfig = to_dataclass(cfg, where="infer")
    if "fbx" in config.export:
        blender_executable()  # before any work: one line saying how to install it, exit status 2
    if "usd" in config.export:
        require_usd()         # likewise for usd-core
    out_dir = Path(config.out_dir) if config.out_dir else default_out_dir()
    source = Path(config.expressions) if config.expressions is not None else None
    if source is not None and source.is_dir():
        rows = run_folder(config, source, out_dir)
        print_summary(rows)
        if not any(r["status"] == "ok" for r in rows):
            raise InputError(f"expressions={source}: no take could be run (reasons above)")
        return rows
    if source is None:
        print("expressions: none given; running the built-in demo take (12 s: talking, a head turn, a nod, a tilt)")
    models = load_models(config)
    row = run_take(config, models, None if source is None else str(source), out_dir)
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in row["stage_seconds"].items())
    print(f"{out_dir}: {row['frames']} frames at {row['fps']:g} fps ({stages})\n"
          f"  open {out_dir / 'plot.png'} (the tracks), params.npz / params.csv (per-frame parameters)"
          + (", meshes/" if config.meshes else ""))
    print(json.dumps({k: row[k] for k in ("frames", "fps", "tau_range", "max_joint_deg")}))
    return [row]
