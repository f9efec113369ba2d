"""Training entry point: ``python train.py task=<larynx_transformer|head2neck> [overrides]``.

The loop is task-agnostic; ``tasks/<name>.py`` supplies the model, batches,
losses and evaluation.  Each run writes to its hydra run directory
(``runs/<task>/<timestamp>`` unless ``hydra.run.dir=...``):

- ``checkpoints/last.pt``: model, optimiser, scheduler, step and the resolved
  config, written atomically every ``trainer.checkpoint_every`` steps and at
  the end; ``resume=true`` with the same ``hydra.run.dir`` continues from it.
  The resumed run's config must equal the checkpoint's except for the
  run-control keys (``RUN_CONTROL_KEYS``: when to stop, log, evaluate and save,
  threads, the progress bar), else InputError listing the differences;
- ``metrics.csv``: ``step,split,name,value`` rows (train losses, validation);
  on resume the rows after the checkpoint's step (logged before an
  interruption, and about to be logged again) are dropped;
- ``eval.json``: the final evaluation, with the task's baselines.

Reproducibility: the model is initialised after ``torch.manual_seed(seed)``;
step ``s`` seeds torch's global generator (dropout, the model's own draws) and
the generator of its batch with two independent seeds of
``numpy.random.SeedSequence([seed, s])`` (:func:`step_seeds`), so the same
config gives the same weights, and an interrupted run resumed from a
checkpoint gives the same weights as an uninterrupted one.
"""
from __future__ import annotations

import json
import math
import sys
import time
from pathlib import Path

import hydra
import numpy as np
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

import tasks
from data.cli import compose_config
from data.errors import InputError
from data.files import write_text
from models.checkpoint import load_checkpoint, load_state, save_checkpoint

# Config keys a resumed run may change (configs/trainer/*.yaml): they steer the run, not what it computes.
RUN_CONTROL_KEYS = ("resume", "trainer.stop_after", "trainer.progress", "trainer.threads", "trainer.log_every",
                    "trainer.eval_every", "trainer.checkpoint_every")


def step_seeds(seed: int, step: int) -> tuple[int, int]:
    """(torch's global seed, the batch generator's seed) for training step ``step``: two independent
    64-bit seeds drawn from ``numpy.random.SeedSequence([seed, step])``."""
    global_seed, batch_seed = np.random.SeedSequence([seed, step]).generate_state(2, np.uint64)
    return int(global_seed), int(batch_seed)


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
    ``RUN_CONTROL_KEYS``; the message lists each differing dotted key with its old and new value."""
    for key in ("config", "optimizer", "scheduler", "step"):
        if key not in state:
            raise InputError(f"{path}: checkpoint has no '{key}' entry, so it cannot be resumed; expected one "
                             f"written by train.py")
    if state["task"] != cfg.task.name:
        raise InputError(f"{path}: checkpoint of task '{state['task']}', but resume=true runs task "
                         f"'{cfg.task.name}'")
    old, new = flatten(state["config"]), flatten(OmegaConf.to_container(cfg, resolve=True))
    absent = "<absent>"
    changed = [f"{key}: {old.get(key, absent)!r} -> {new.get(key, absent)!r}" for key in sorted(set(old) | set(new))
               if key not in RUN_CONTROL_KEYS and old.get(key, absent) != new.get(key, absent)]
    if changed:
        raise InputError(f"{path}: resume=true with a config that differs from the checkpoint's "
                         f"({'; '.join(changed)}); only {', '.join(RUN_CONTROL_KEYS)} may change: "
                         f"resume with the run's settings or start a new run")


def lr_factor(step: int, warmup: int, total: int, min_factor: float) -> float:
    """Linear warm-up over ``warmup`` steps, then cosine decay to ``min_factor`` at ``total``."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_factor + (1 - min_factor) * 0.5 * (1 + math.cos(math.pi * progress))


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


def fit(cfg: DictConfig, run_dir: Path) -> dict[str, float]:
    """Train the task of ``cfg`` in ``run_dir``; returns the final evaluation."""
    trainer = cfg.trainer
    run_dir.mkdir(parents=True, exist_ok=True)
    if trainer.threads:
        torch.set_num_threads(int(trainer.threads))
    checkpoint_path = run_dir / "checkpoints" / "last.pt"
    state = None
    if cfg.resume:
        if not checkpoint_path.exists():
            raise InputError(f"{checkpoint_path}: not found, so resume=true has nothing to continue; pass "
                             f"hydra.run.dir=<the run's directory>")
        state = load_checkpoint(checkpoint_path)
        check_resumable(state, cfg, checkpoint_path)
    torch.manual_seed(cfg.seed)
    task = tasks.build(cfg)
    model = task.model
    optimizer = torch.optim.AdamW(
        model.parameters(), lr=cfg.optim.lr, betas=tuple(cfg.optim.betas), weight_decay=cfg.optim.weight_decay
    )
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: lr_factor(s, cfg.optim.warmup_steps, trainer.max_steps, cfg.optim.min_lr_factor)
    )
    start = 0
    log = MetricsLog(run_dir / "metrics.csv")
    if state is not None:
        for name, part in (("model", model), ("optimizer", optimizer), ("scheduler", scheduler)):
            load_state(part, state[name], checkpoint_path, name)
        start = int(state["step"])
        log.truncate(start)

    def save(step: int) -> None:
        save_checkpoint(checkpoint_path, {
            "task": cfg.task.name, "model_config": task.model_config(), "model": model.state_dict(),
            "optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(), "step": step,
            "config": OmegaConf.to_container(cfg, resolve=True),
        })

    stop = trainer.max_steps if trainer.stop_after is None else min(trainer.max_steps, trainer.stop_after)
    progress = tqdm(range(start, stop), initial=start, total=stop, desc=cfg.task.name,
                    disable=not trainer.progress, dynamic_ncols=True)
    running: dict[str, float] = {}
    count = 0
    started = time.perf_counter()
    for step in progress:
        global_seed, batch_seed = step_seeds(int(cfg.seed), step)
        torch.manual_seed(global_seed)
        batch = task.batch(step, torch.Generator().manual_seed(batch_seed))
        model.train()
        loss, metrics = task.loss(batch, step)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if trainer.grad_clip:
            torch.nn.utils.clip_grad_norm_(model.parameters(), trainer.grad_clip)
        optimizer.step()
        scheduler.step()
        for k, v in metrics.items():
            running[k] = running.get(k, 0.0) + float(v)
        count += 1
        done = step + 1
        if done % trainer.log_every == 0 or done == stop:
            averaged = {k: v / count for k, v in running.items()}
            log.log(done, "train", {**averaged, "lr": scheduler.get_last_lr()[0]})
            progress.set_postfix({k: f"{v:.4g}" for k, v in list(averaged.items())[:3]})
            running, count = {}, 0
        if trainer.eval_every and done % trainer.eval_every == 0 and done != stop:
            model.eval()
            with torch.no_grad():
                log.log(done, "val", task.evaluate())
        if done % trainer.checkpoint_every == 0 or done == stop:
            save(done)
    elapsed = time.perf_counter() - started
    if stop < trainer.max_steps:
        print(f"stopped after step {stop} of {trainer.max_steps} (trainer.stop_after); resume=true continues")
        return {}
    model.eval()
    with torch.no_grad():
        final = task.evaluate(final=True)
    final = {k: float(v) for k, v in final.items()}
    final["train_seconds"] = elapsed
    log.log(stop, "final", final)
    write_text(run_dir / "eval.json", json.dumps(final, indent=2) + "\n")
    print(f"checkpoint: {checkpoint_path}\nevaluation: {run_dir / 'eval.json'}")
    return final


@hydra.main(version_base=None, config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    try:
        fit(cfg, Path(HydraConfig.get().runtime.output_dir))
    except InputError as e:  # bad data or a refused resume: the message, status 2, no traceback (data.cli)
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


def check_command_line(argv: list[str]) -> None:
    """Compose the config once before hydra runs it, so an unknown key, a wrong type or a missing value is
    one line and exit status 2 (data.cli) rather than hydra's report.  Sweeps (``-m``) and hydra's own
    flags and keys are left to hydra."""
    if any(arg.startswith("-") for arg in argv):
        return
    try:
        compose_config("train", [arg for arg in argv if not arg.startswith(("hydra.", "hydra/", "+hydra"))])
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":
    check_command_line(sys.argv[1:])
    main()
