"""Retrain the shipped models with the commands in their manifest and compare the figures.

    python benchmarks/retrain_pretrained.py [--only head2neck] [--ship]

For each entry of ``models/pretrained/manifest.json``: run its ``command`` (``python train.py ...``) into a
fresh run folder under ``runs/retrain/``, then print the shipped and the retrained evaluation side by side,
and whether the weights are identical (training is seeded, so on the same code, torch and machine they
are).  ``--ship`` replaces the shipped file and its manifest entry with the retrained run.  Not part of the
tests: each run takes minutes.
"""
from __future__ import annotations

import argparse
import json
import shlex
import subprocess
import sys
from datetime import datetime
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from models.checkpoint import load_checkpoint  # noqa: E402
from models.pretrained import PRETRAINED, read_manifest  # noqa: E402
from tools.ship_model import ship  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--only", action="append", help="retrain only this manifest entry (repeatable)")
    parser.add_argument("--ship", action="store_true", help="replace the shipped files with the retrained runs")
    args = parser.parse_args()
    manifest = read_manifest()
    if not manifest:
        raise SystemExit(f"{PRETRAINED / 'manifest.json'}: nothing is shipped")
    for name, entry in manifest.items():
        if args.only and name not in args.only:
            continue
        run_dir = REPO / "runs" / "retrain" / f"{name}_{datetime.now():%Y-%m-%d_%H-%M-%S}"
        command = shlex.split(entry["command"])
        if command[:2] != ["python", "train.py"]:
            print(f"{name}: command {entry['command']!r} is not a train.py run; skipped")
            continue
        print(f"{name}: {entry['command']} -> {run_dir}", flush=True)
        subprocess.run([sys.executable, "train.py", *command[2:], "trainer.progress=false",
                        f"hydra.run.dir={run_dir}"], cwd=REPO, check=True)
        retrained = json.loads((run_dir / "eval.json").read_text())
        shipped_weights = load_checkpoint(PRETRAINED / entry["file"])["model"]
        new_weights = load_checkpoint(run_dir / "checkpoints" / "last.pt")["model"]
        same = shipped_weights.keys() == new_weights.keys() and all(
            torch.equal(shipped_weights[k], new_weights[k]) for k in shipped_weights)
        print(f"{'metric':<40} {'shipped':>12} {'retrained':>12}")
        for key in sorted(set(entry["eval"]) | set(retrained)):
            old, new = entry["eval"].get(key), retrained.get(key)
            fmt = lambda v: f"{v:12.5g}" if isinstance(v, (int, float)) else f"{str(v):>12}"  # noqa: E731
            print(f"{key:<40} {fmt(old)} {fmt(new)}")
        print(f"weights identical to the shipped file: {same}\n")
        if args.ship:
            ship(run_dir, name, entry["command"])
            print(f"{name}: shipped the retrained run")


if __name__ == "__main__":
    main()
