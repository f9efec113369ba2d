"""infer.py speed: a one-minute 60 fps capture to params.npz (no meshes), with the time of each stage.

    python benchmarks/bench_infer.py [--seconds 60] [--fps 60] [--repeats 3] [--checkpoint default]
        [--head2neck default]

The capture is written as a Live Link Face CSV (55 ARKit columns, HeadYaw/Pitch/Roll, 60 fps timecodes)
from the demo take's generator, so the read stage parses a real-format file.  Stages: read (CSV ->
ExpressionTrack), resample, larynx (the transformer streamed over psi), head2neck (MLP + exact
correction), write (params.npz + params.csv); the plot is off.  Target: under 5 s end to end.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.demo_take import demo_take  # noqa: E402
from data.expressions import EXPRESSION_NAMES, arkit_name  # noqa: E402


def write_capture(path: Path, seconds: float, fps: float) -> int:
    """A Live Link Face-style CSV of ``seconds`` at ``fps``; returns its row count."""
    take = demo_take(fps=fps)
    reps = int(np.ceil(seconds / take.time[-1]))
    psi = np.concatenate([take.psi] * reps)[: int(seconds * fps)]
    head = np.concatenate([take.head_ypr] * reps)[: len(psi)]
    columns = {}
    for k, name in enumerate(EXPRESSION_NAMES):
        arkit = arkit_name(name)
        if arkit is not None:
            columns.setdefault(arkit[0].upper() + arkit[1:], psi[:, k])
    lines = ["Timecode,BlendShapeCount," + ",".join(columns) + ",HeadYaw,HeadPitch,HeadRoll"]
    for i in range(len(psi)):
        t = i / fps
        code = f"10:{int(t // 60):02d}:{int(t % 60):02d}:{(t % 1) * 60:06.3f}"
        values = ",".join(f"{columns[c][i]:.6f}" for c in columns)
        lines.append(f"{code},{len(columns)},{values},{head[i, 0]:.6f},{head[i, 1]:.6f},{head[i, 2]:.6f}")
    path.write_text("\n".join(lines) + "\n")
    return len(psi)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--fps", type=float, default=60.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--checkpoint", default="default")
    parser.add_argument("--head2neck", default="default")
    args = parser.parse_args()
    torch.set_num_threads(1)
    from base.cli import compose_config, to_dataclass
    from motion.pipeline.models import load_models
    from motion.pipeline.take import run_take

    with tempfile.TemporaryDirectory() as tmp:
        capture = Path(tmp) / "capture.csv"
        rows = write_capture(capture, args.seconds, args.fps)
        cfg = to_dataclass(compose_config("infer", [f"checkpoint={args.checkpoint}", f"head2neck={args.head2neck}",
                                                    "plot=false"]))
        started = time.perf_counter()
        models = load_models(cfg)
        load_seconds = time.perf_counter() - started
        print(f"capture: {rows} rows ({args.seconds:g} s at {args.fps:g} fps); models loaded in {load_seconds:.2f} s")
        for repeat in range(args.repeats):
            started = time.perf_counter()
            row = run_take(cfg, models, str(capture), Path(tmp) / f"out{repeat}", announce=lambda message: None)
            total = time.perf_counter() - started
            stages = "  ".join(f"{k} {v:.3f}" for k, v in row["stage_seconds"].items())
            print(f"run {repeat}: {total:.2f} s total ({row['frames']} output frames at {row['fps']:g} fps)  "
                  f"stages (s): {stages}")


if __name__ == "__main__":
    main()
