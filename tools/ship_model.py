"""Ship a finished ``train.py`` run as a model of ``models/pretrained/`` (release tooling, outside the layers):

    python -m tools.ship_model run=runs/<task>/<time> name=<file stem> command="python train.py ..."

Writes the run's weights as ``models/pretrained/<name>.pt`` (weights only: ``task``, ``model_config``,
``model``, ``step``; no optimiser state), checks that they rebuild, and enters the file in the manifest with
its sha256, the command, the commit (:func:`git_commit`) and the run's ``eval.json``.  :func:`ship_file`
enters a file made otherwise (the swallow template of ``benchmarks/make_swallow_template.py``).
``benchmarks/retrain_pretrained.py --ship`` retrains and ships every entry with its manifest command.
"""
from __future__ import annotations

import json
import os
import subprocess
from dataclasses import dataclass
from pathlib import Path

import torch

from base.cli import REQUIRED, register_config, run_cli
from base.errors import InputError
from base.files import write_text
from models.checkpoint import load_checkpoint, load_model, save_checkpoint
from models.pretrained import MANIFEST, PRETRAINED, read_manifest, sha256

REPO = Path(__file__).resolve().parents[1]


@dataclass
class ShipCli:
    """``python -m tools.ship_model``: ship a finished train.py run (``configs/ship_model.yaml``)."""

    run: str = REQUIRED       # the run directory (runs/<task>/<time>)
    name: str = REQUIRED      # file stem under models/pretrained/
    command: str = REQUIRED   # the command that produced the run, for the manifest
    checkpoint: str | None = None  # null: the weights eval.json scored (best.pt with trainer.restore_best)


register_config("ship_model_schema", ShipCli)


def git_commit() -> str:
    """HEAD's commit, "+uncommitted changes" when a tracked file other than the shipped files and the manifest
    differs from it (those change as each model is shipped, so they do not count)."""
    try:
        out = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True, cwd=REPO)
        shipped = [f":(exclude)models/pretrained/{p}" for p in ("*.pt", "*.csv", "manifest.json")]
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no", "--", ".", *shipped],
                               capture_output=True, text=True, cwd=REPO).stdout.strip()
        return out.stdout.strip() + ("+uncommitted changes" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def evaluated_checkpoint(run_dir: Path) -> str:
    """The checkpoint whose weights a run's eval.json scored: ``best.pt`` when the run restored its best weights
    (``trainer.restore_best``), else ``last.pt``."""
    last = load_checkpoint(run_dir / "checkpoints" / "last.pt")
    restored = bool(last.get("config", {}).get("trainer", {}).get("restore_best"))
    return "best.pt" if restored and (run_dir / "checkpoints" / "best.pt").is_file() else "last.pt"


def ship(run_dir: str | os.PathLike, name: str, command: str, checkpoint: str | None = None) -> dict:
    """Write the weights of a ``train.py`` run as ``models/pretrained/<name>.pt`` and its manifest entry
    (``checkpoint`` None: the weights eval.json scored, :func:`evaluated_checkpoint`)."""
    run_dir = Path(run_dir)
    checkpoint = evaluated_checkpoint(run_dir) if checkpoint is None else checkpoint
    state = load_checkpoint(run_dir / "checkpoints" / checkpoint)
    evaluation_path = run_dir / "eval.json"
    if not evaluation_path.is_file():
        raise InputError(f"{evaluation_path}: not found; ship a finished run (it writes eval.json at the end)")
    evaluation = json.loads(evaluation_path.read_text())
    path = PRETRAINED / f"{name}.pt"
    weights = {"task": state["task"], "model_config": state["model_config"], "step": state.get("step"),
               "model": {k: v.clone() for k, v in state["model"].items()}}
    save_checkpoint(path, weights)
    load_model(path, task=state["task"])  # it must rebuild
    manifest = read_manifest()
    manifest[name] = {"file": path.name, "task": state["task"], "sha256": sha256(path), "bytes": path.stat().st_size,
                      "command": command, "commit": git_commit(), "eval": evaluation,
                      "trained_on": "built-in procedural rig and synthetic data (no third-party data)"}
    write_text(MANIFEST, json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return manifest[name]


def ship_file(path: str | os.PathLike, name: str, task: str, command: str, evaluation: dict) -> dict:
    """Enter a file already under ``models/pretrained/`` (e.g. the swallow template) in the manifest."""
    path = Path(path)
    if path.parent.resolve() != PRETRAINED.resolve():
        raise InputError(f"{path}: shipped files live in {PRETRAINED}")
    manifest = read_manifest()
    manifest[name] = {"file": path.name, "task": task, "sha256": sha256(path), "bytes": path.stat().st_size,
                      "command": command, "commit": git_commit(), "eval": evaluation,
                      "trained_on": "synthetic data from the project's own generators (no third-party data)"}
    write_text(MANIFEST, json.dumps(manifest, indent=2, sort_keys=True) + "\n")
    return manifest[name]


def run(cfg) -> None:
    entry = ship(cfg.run, cfg.name, cfg.command, cfg.checkpoint)
    print(f"{PRETRAINED / entry['file']}: {entry['bytes'] / 1e6:.2f} MB, sha256 {entry['sha256'][:12]}..., "
          f"task {entry['task']}")


if __name__ == "__main__":
    torch.set_num_threads(1)
    run_cli("ship_model", run, doc=__doc__)
