"""``python -m models.pretrained``: ship a finished train.py run (its settings, registered as a schema, and
the command)."""
from __future__ import annotations

from dataclasses import dataclass

from base.cli import REQUIRED, register_config
from models.pretrained import PRETRAINED, ship


@dataclass
class ShipCli:
    """``python -m models.pretrained``: ship a finished train.py run."""

    run: str = REQUIRED       # the run directory (runs/<task>/<time>)
    name: str = REQUIRED      # file stem under models/pretrained/
    command: str = REQUIRED   # the command that produced the run, for the manifest
    checkpoint: str | None = None  # null: the weights eval.json scored (best.pt with trainer.restore_best)


register_config("pretrained_schema", ShipCli)


def run(cfg) -> None:
    entry = ship(cfg.run, cfg.name, cfg.command, cfg.checkpoint)
    print(f"{PRETRAINED / entry['file']}: {entry['bytes'] / 1e6:.2f} MB, sha256 {entry['sha256'][:12]}..., "
          f"task {entry['task']}")
