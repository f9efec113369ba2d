"""A run's folder: where its checkpoints, metrics and evaluation go, and whether a run may continue it.

- ``checkpoints/last.pt``: model, optimiser, scheduler, step and the resolved config, written
  atomically every ``trainer.checkpoint_every`` steps and at the end; ``resume=true`` with the same
  ``hydra.run.dir`` continues from it.  The resumed run's config must equal the checkpoint's except for
  the run-control keys (``RUN_CONTROL_KEYS``: when to stop, log, evaluate and save, threads, the
  progress bar, the device), else InputError listing the differences;
- ``checkpoints/best.pt``: the weights of the lowest validation ``val_loss`` (``tasks.validation``);
- ``metrics.csv``: ``step,split,name,value`` rows (:class:`MetricsLog`); on resume the rows after the
  checkpoint's step (logged before an interruption, and about to be logged again) are dropped;
- ``eval.json``: the final evaluation, with the task's baselines.

A run refused before it saved anything leaves no folder behind (:func:`discard_unstarted_run`).
"""
from __future__ import annotations

import json
import shutil
from pathlib import Path

from omegaconf import DictConfig, OmegaConf

from base.errors import InputError
from base.files import write_text
from models.checkpoint import load_checkpoint, save_checkpoint

# Config keys a resumed run may change (configs/trainer/*.yaml): they steer the run, not what it computes.
RUN_CONTROL_KEYS = ("resume", "trainer.stop_after", "trainer.progress", "trainer.threads", "trainer.member_workers",
                    "trainer.log_every", "trainer.eval_every", "trainer.checkpoint_every", "trainer.device")
# ... except when validation chooses what is trained (early stopping, best weights): then it may not change.
SELECTION_KEYS = ("trainer.eval_every",)


def flatten(tree: dict, prefix: str = "") -> dict:
    """Nested dicts -> {dotted key: leaf value} (lists are leaves)."""
    out = {}
    for key, value in tree.items():
        if isinstance(value, dict):
            out.update(flatten(value, f"{prefix}{key}."))
        else:
            out[f"{prefix}{key}"] = value
    return out


def check_resumable(state: dict, cfg: DictConfig, path: Path) -> None:
    """InputError unless the checkpoint ``state`` was written by this task with the same config, up to
    ``RUN_CONTROL_KEYS`` (less ``SELECTION_KEYS`` when the run stops early or restores its best weights);
    the message lists each differing dotted key with its old and new value."""
    for key in ("config", "optimizer", "scheduler", "step"):
        if key not in state:
            raise InputError(f"{path}: checkpoint has no '{key}' entry, so it cannot be resumed; expected one "
                             f"written by train.py")
    if state["task"] != cfg.task.name:
        raise InputError(f"{path}: checkpoint of task '{state['task']}', but resume=true runs task "
                         f"'{cfg.task.name}'")
    old, new = flatten(state["config"]), flatten(OmegaConf.to_container(cfg, resolve=True))
    control = RUN_CONTROL_KEYS
    if old.get("trainer.early_stopping_patience") is not None or old.get("trainer.restore_best"):
        control = tuple(key for key in RUN_CONTROL_KEYS if key not in SELECTION_KEYS)
    absent = "<absent>"
    changed = [f"{key}: {old.get(key, absent)!r} -> {new.get(key, absent)!r}" for key in sorted(set(old) | set(new))
               if key not in control and old.get(key, absent) != new.get(key, absent)]
    if changed:
        raise InputError(f"{path}: resume=true with a config that differs from the checkpoint's "
                         f"({'; '.join(changed)}); only {', '.join(control)} may change: "
                         f"resume with the run's settings or start a new run")


class MetricsLog:
    """Append-only ``step,split,name,value`` CSV (a row per number, so tasks may log anything)."""

    HEADER = "step,split,name,value\n"

    def __init__(self, path: Path):
        self.path = path
        if not path.exists():
            write_text(path, self.HEADER)

    def truncate(self, step: int) -> None:
        """Keep the rows of steps up to ``step`` except the final evaluation (rewritten atomically): what a
        run resumed from the checkpoint of ``step`` has not logged again yet."""
        lines = self.path.read_text().splitlines(keepends=True)
        kept = [self.HEADER]
        for number, line in enumerate(lines[1:], start=2):
            cells = line.rstrip("\n").split(",")
            if len(cells) != 4 or not cells[0].isdigit():
                raise InputError(f"{self.path}: line {number} is {line.strip()!r}, expected step,split,name,value "
                                 f"with an integer step")
            if int(cells[0]) <= step and cells[1] != "final":
                kept.append(line)
        write_text(self.path, "".join(kept))

    def log(self, step: int, split: str, metrics: dict[str, float]) -> None:
        with open(self.path, "a") as f:
            for name, value in metrics.items():
                f.write(f"{step},{split},{name},{float(value):.6g}\n")


class RunFolder:
    """The files of the run in ``path`` (only rank 0, ``writer``, creates the folder)."""

    def __init__(self, path: Path, writer: bool = True):
        self.path = path
        self.last = path / "checkpoints" / "last.pt"
        self.best = path / "checkpoints" / "best.pt"
        self.metrics = path / "metrics.csv"
        self.evaluation = path / "eval.json"
        if writer:
            path.mkdir(parents=True, exist_ok=True)

    def resume_state(self, cfg: DictConfig) -> dict | None:
        """The checkpoint ``resume=true`` continues (checked against ``cfg``), None for a new run;
        InputError for a new run in a used folder, or a resume with nothing (or something else) to continue."""
        if not cfg.resume and self.last.exists():
            raise InputError(f"{self.last}: this run directory already holds a run; resume=true continues it, "
                             f"or choose another hydra.run.dir")
        if not cfg.resume:
            return None
        if not self.last.exists():
            raise InputError(f"{self.last}: not found, so resume=true has nothing to continue; pass "
                             f"hydra.run.dir=<the run's directory>")
        state = load_checkpoint(self.last)
        check_resumable(state, cfg, self.last)
        return state

    def save_last(self, state: dict) -> None:
        save_checkpoint(self.last, state)

    def save_best(self, weights: dict, val_loss: float) -> None:
        save_checkpoint(self.best, {**weights, "val_loss": val_loss})

    def write_evaluation(self, final: dict[str, float]) -> None:
        write_text(self.evaluation, json.dumps(final, indent=2) + "\n")


def discard_unstarted_run(run_dir: Path) -> None:
    """Remove what hydra wrote into ``run_dir`` (``.hydra/``, the job's log) for a run refused before it saved
    anything, the folder if that leaves it empty, and the folders above it inside the working directory that
    are left empty (``runs/<task>/`` of a first run): a refused run leaves no half-made run folder (nor the
    folders of an ensemble's members, ``tasks.members``, that saved nothing)."""
    if not run_dir.is_dir() or any(run_dir.rglob("checkpoints")):
        return
    shutil.rmtree(run_dir / "members", ignore_errors=True)
    shutil.rmtree(run_dir / ".hydra", ignore_errors=True)
    for log_file in run_dir.glob("*.log"):
        log_file.unlink(missing_ok=True)
    run_dir, cwd = run_dir.resolve(), Path.cwd().resolve()
    above = [folder for folder in run_dir.parents if cwd in folder.parents]  # inside the working directory
    for folder in [run_dir, *above]:
        if any(folder.iterdir()):
            break
        folder.rmdir()
