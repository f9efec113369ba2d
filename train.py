"""Training entry point: ``python train.py task=<larynx_transformer|head2neck> [overrides]``.

The loop is task-agnostic; ``tasks/<name>.py`` supplies the model, batches,
losses and evaluation.  Each run writes to its hydra run directory
(``runs/<task>/<timestamp>`` unless ``hydra.run.dir=...``):

- ``checkpoints/last.pt``: model, optimiser, scheduler and step, written
  atomically every ``trainer.checkpoint_every`` steps and at the end;
  ``resume=true`` with the same ``hydra.run.dir`` continues from it;
- ``metrics.csv``: ``step,split,name,value`` rows (train losses, validation);
- ``eval.json``: the final evaluation, with the task's baselines.

Reproducibility: step ``s`` seeds torch with ``seed * 1_000_003 + s`` before
drawing its batch and running the model, so the same config gives the same
weights, and an interrupted run resumed from a checkpoint gives the same
weights as an uninterrupted one.
"""
from __future__ import annotations

import json
import math
import time
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from tqdm import tqdm

import tasks
from data.io import write_text
from models.checkpoint import load_checkpoint, save_checkpoint


def step_seed(seed: int, step: int) -> int:
    return (seed * 1_000_003 + step) % (2**63 - 1)


def lr_factor(step: int, warmup: int, total: int, min_factor: float) -> float:
    """Linear warm-up over ``warmup`` steps, then cosine decay to ``min_factor`` at ``total``."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_factor + (1 - min_factor) * 0.5 * (1 + math.cos(math.pi * progress))


class MetricsLog:
    """Append-only ``step,split,name,value`` CSV (a row per number, so tasks may log anything)."""

    def __init__(self, path: Path):
        self.path = path
        if not path.exists():
            path.write_text("step,split,name,value\n")

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
    torch.manual_seed(cfg.seed)
    task = tasks.build(cfg)
    model = task.model
    optimizer = torch.optim.AdamW(
        model.parameters(), lr=cfg.optim.lr, betas=tuple(cfg.optim.betas), weight_decay=cfg.optim.weight_decay
    )
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: lr_factor(s, cfg.optim.warmup_steps, trainer.max_steps, cfg.optim.min_lr_factor)
    )
    checkpoint_path = run_dir / "checkpoints" / "last.pt"
    start = 0
    if cfg.resume:
        if not checkpoint_path.exists():
            raise FileNotFoundError(f"resume=true but {checkpoint_path} does not exist; pass hydra.run.dir=<run dir>")
        state = load_checkpoint(checkpoint_path)
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        scheduler.load_state_dict(state["scheduler"])
        start = int(state["step"])
    log = MetricsLog(run_dir / "metrics.csv")

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
        seed = step_seed(cfg.seed, step)
        torch.manual_seed(seed)
        batch = task.batch(step, torch.Generator().manual_seed(seed))
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
    fit(cfg, Path(HydraConfig.get().runtime.output_dir))


if __name__ == "__main__":
    main()
