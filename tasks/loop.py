"""The training loop: train one network of a task (``tasks/<name>``) for ``trainer.max_steps`` steps in a run
folder (an ensemble's members are runs of it, ``tasks.members``).

:func:`fit` trains, validates, checkpoints and evaluates; the files it writes, and how a run resumes,
are ``tasks.run_folder``'s; validation's record and early stopping ``tasks.validation``'s; training on
several processes ``tasks.distributed``'s.

Reproducibility: the model is initialised after ``torch.manual_seed(seed)``; step ``s`` seeds torch's
global generator (dropout, the model's own draws) and the generator of its batch with two independent
seeds of ``numpy.random.SeedSequence([seed, s])`` (:func:`step_seeds`), so the same config gives the
same weights, and an interrupted run resumed from a checkpoint gives the same weights as an
uninterrupted one.

Several processes (``torchrun --nproc_per_node=N train.py ...``): rank 0 alone writes the checkpoints,
metrics and progress bar, and runs the final evaluation; every rank validates during training (rank 0's
result decides early stopping).  Rank ``r > 0`` seeds torch's global generator with :func:`rank_seed`
(its own draws, e.g. dropout masks: with dropout the ranks' masks differ from one process's, so equal
weights need dropout 0).  The world size is not part of the config: a run may be resumed with another
number of processes, continuing the same computation up to float rounding.
"""
from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

import tasks
from base.cli import to_dataclass
from base.errors import InputError
from base.progress import progress_bar
from models.checkpoint import load_checkpoint, load_state
from tasks.distributed import (
    Ranks,
    TaskParallel,
    from_rank0,
    launched_ranks,
    mean_over_ranks,
    process_group,
    resolve_device,
    split_batch,
    to_device,
)
from tasks.run_folder import MetricsLog, RunFolder
from tasks.validation import Validation


def step_seeds(seed: int, step: int) -> tuple[int, int]:
    """(torch's global seed, the batch generator's seed) for training step ``step``: two independent
    64-bit seeds drawn from ``numpy.random.SeedSequence([seed, step])``."""
    global_seed, batch_seed = np.random.SeedSequence([seed, step]).generate_state(2, np.uint64)
    return int(global_seed), int(batch_seed)


def rank_seed(seed: int, step: int, rank: int) -> int:
    """Torch's global seed at ``step`` on rank ``rank``: rank 0 keeps :func:`step_seeds`' (so one process is
    unchanged), the other ranks draw theirs from ``numpy.random.SeedSequence([seed, step, rank])``."""
    if rank == 0:
        return step_seeds(seed, step)[0]
    return int(np.random.SeedSequence([seed, step, rank]).generate_state(1, np.uint64)[0])


def lr_factor(step: int, warmup: int, total: int, min_factor: float) -> float:
    """Linear warm-up over ``warmup`` steps, then cosine decay to ``min_factor`` at ``total``."""
    if step < warmup:
        return (step + 1) / warmup
    progress = min(1.0, (step - warmup) / max(1, total - warmup))
    return min_factor + (1 - min_factor) * 0.5 * (1 + math.cos(math.pi * progress))


def fit(cfg: DictConfig, run_dir: Path, data=None, ranks: Ranks | None = None) -> dict[str, float]:
    """Train the network of ``cfg`` in ``run_dir`` on ``data`` (the task module's ``load_data(cfg)``; None: the
    task loads its own) among ``ranks`` (None: the processes torchrun launched); returns the final evaluation (on
    rank 0; ``{}`` on the other ranks and when ``trainer.stop_after`` ends the run)."""
    trainer = to_dataclass(cfg.trainer, where="trainer")
    ranks = launched_ranks() if ranks is None else ranks
    if trainer.threads:
        torch.set_num_threads(int(trainer.threads))
    task_moves = hasattr(tasks.task_module(cfg.task.name).Task, "to")
    device = resolve_device(trainer.device, ranks.local_rank, task_moves)
    if trainer.device == "auto" and device.type == "cpu" and torch.cuda.is_available() and ranks.main:
        print(f"note: task {cfg.task.name} cannot run on CUDA (its Task has no to(device)): training on the CPU")
    if trainer.amp and device.type != "cuda":
        raise InputError(f"trainer.amp=true: mixed precision runs on CUDA only, and this run is on the CPU "
                         f"(trainer.device={trainer.device}); set trainer.amp=false")
    with process_group(ranks, device):
        folder = RunFolder(Path(from_rank0(str(run_dir), ranks)), writer=ranks.main)
        state = folder.resume_state(cfg)
        torch.manual_seed(cfg.seed)
        task = tasks.build(cfg, data)
        return Training(cfg, task_length(trainer, task, cfg.task.name, ranks.main), task, folder, ranks,
                        device, state).run()


def task_length(trainer, task, name: str, announce: bool):
    """``trainer`` with ``max_steps`` set: the task's own choice for its data when it is null."""
    if trainer.max_steps is not None:
        return trainer
    if getattr(task, "total_steps", None) is None:
        raise InputError(f"trainer.max_steps=null: task {name} does not choose its length; set trainer.max_steps")
    trainer = dataclasses.replace(trainer, max_steps=int(task.total_steps))
    if announce:
        print(f"{name}: {trainer.max_steps} training steps for these data (trainer.max_steps=null)")
    return trainer


class RunningMeans:
    """The train metrics summed since the last log, and how many steps they cover."""

    def __init__(self):
        self.sums: dict[str, float] = {}
        self.count = 0

    def add(self, metrics: dict[str, float]) -> None:
        for k, v in metrics.items():
            self.sums[k] = self.sums.get(k, 0.0) + float(v)
        self.count += 1

    def take(self) -> dict[str, float]:
        """The means since the last ``take``, starting afresh."""
        means = {k: v / self.count for k, v in self.sums.items()}
        self.sums, self.count = {}, 0
        return means


class Training:
    """One run of the loop: the task's model with its optimiser, learning-rate schedule and gradient
    scaler, resumed from the checkpoint ``state`` when there is one, and its validation record."""

    def __init__(self, cfg: DictConfig, trainer, task, folder: RunFolder, ranks: Ranks, device: torch.device,
                 state: dict | None = None):
        self.cfg, self.trainer, self.task, self.folder = cfg, trainer, task, folder
        self.ranks, self.device = ranks, device
        if device.type != "cpu":
            task.to(device)
        self.model = task.model
        self.optimizer = torch.optim.AdamW(self.model.parameters(), lr=cfg.optim.lr, betas=tuple(cfg.optim.betas),
                                           weight_decay=cfg.optim.weight_decay)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(
            self.optimizer,
            lambda s: lr_factor(s, cfg.optim.warmup_steps, trainer.max_steps, cfg.optim.min_lr_factor))
        self.scaler = torch.amp.GradScaler(device.type, enabled=trainer.amp)
        self.log = MetricsLog(folder.metrics) if ranks.main else None
        self.start = 0
        if state is not None:
            self.restore(state)
        self.validation = Validation(trainer.early_stopping_patience, state.get("validation") if state else None)
        self.selecting = trainer.early_stopping_patience is not None or trainer.restore_best
        # DDP after the resumed weights are loaded (it starts every rank from rank 0's parameters).
        self.parallel = None
        if ranks.world > 1:
            self.parallel = TaskParallel(self.model, device_ids=[device.index] if device.type == "cuda" else None,
                                         forward_sync_buffers=False)  # the models' buffers are constants
        self.running = RunningMeans()

    def restore(self, state: dict) -> None:
        """Continue from the checkpoint ``state``: weights, optimiser, schedule, scaler, step, metrics log."""
        path = self.folder.last
        for name, part in (("model", self.model), ("optimizer", self.optimizer), ("scheduler", self.scheduler)):
            load_state(part, state[name], path, name)
        if self.trainer.amp and "scaler" in state:
            load_state(self.scaler, state["scaler"], path, "scaler")
        self.start = int(state["step"])
        if self.ranks.main:
            self.log.truncate(self.start)

    def run(self) -> dict[str, float]:
        """Train from the start step to the stop, validating and checkpointing on the way; then the final
        evaluation (rank 0)."""
        trainer, main = self.trainer, self.ranks.main
        stop = trainer.max_steps if trainer.stop_after is None else min(trainer.max_steps, trainer.stop_after)
        if self.validation.stopped:  # resuming a run that stopped early: only the final evaluation is left
            stop = self.start
        progress = progress_bar(range(self.start, stop), initial=self.start, total=stop, desc=self.cfg.task.name,
                                unit="step", disable=not (trainer.progress and main))
        started = time.perf_counter()
        for step in progress:
            self.running.add(self.train_step(step))
            done = step + 1
            if done % trainer.log_every == 0 or done == stop:
                self.log_train(done, progress)
            # At the last step the final evaluation follows; validate there too only to choose between the
            # last and the best weights (restore_best).
            last = done == trainer.max_steps
            if trainer.restore_best if last else bool(trainer.eval_every) and done % trainer.eval_every == 0:
                self.validate(done)
                if from_rank0(self.validation.patience_spent(), self.ranks) and not last:
                    self.validation.stopped, stop = True, done
                    self.stop_early(done, progress)
            if main and (done % trainer.checkpoint_every == 0 or done == stop):
                self.save(done)
            if self.validation.stopped:
                break
        elapsed = time.perf_counter() - started
        if main and stop == self.start == 0:  # max_steps 0: the model as the task built it
            self.save(0)
        if stop < trainer.max_steps and not self.validation.stopped:
            if main:
                print(f"stopped after step {stop} of {trainer.max_steps} (trainer.stop_after); resume=true continues")
            return {}
        if not main:
            return {}
        return self.final_evaluation(stop, elapsed)

    def train_step(self, step: int) -> dict[str, float]:
        """One optimiser step on the seeded batch of ``step`` (this rank's slice of it); the task's metrics."""
        ranks, device, task = self.ranks, self.device, self.task
        global_seed, batch_seed = step_seeds(int(self.cfg.seed), step)
        torch.manual_seed(global_seed if ranks.rank == 0 else rank_seed(int(self.cfg.seed), step, ranks.rank))
        batch = task.batch(step, torch.Generator().manual_seed(batch_seed))
        if ranks.world > 1:
            batch = getattr(task, "split_batch", split_batch)(batch, ranks.rank, ranks.world)
        if device.type != "cpu":
            batch = to_device(batch, device)
        self.model.train()
        if self.parallel is not None:
            task.model = self.parallel  # the loss's forward passes go through DDP
        try:
            with torch.autocast(device.type, dtype=torch.float16, enabled=self.trainer.amp):
                loss, metrics = task.loss(batch, step)
        finally:
            task.model = self.model
        self.optimizer.zero_grad(set_to_none=True)
        self.scaler.scale(loss).backward()
        if self.trainer.grad_clip:
            self.scaler.unscale_(self.optimizer)
            torch.nn.utils.clip_grad_norm_(self.model.parameters(), self.trainer.grad_clip)
        self.scaler.step(self.optimizer)
        self.scaler.update()
        self.scheduler.step()
        return metrics

    def log_train(self, done: int, progress) -> None:
        """Log the mean of the train metrics since the last log (over the steps and the ranks)."""
        averaged = mean_over_ranks(self.running.take(), self.ranks, self.device)
        if self.ranks.main:
            self.log.log(done, "train", {**averaged, "lr": self.scheduler.get_last_lr()[0]})
            progress.set_postfix({k: f"{v:.4g}" for k, v in list(averaged.items())[:3]})

    def validate(self, done: int) -> None:
        """Score the weights after step ``done``; log the scores and keep the weights if they are the best."""
        self.model.eval()
        with torch.no_grad():
            scores = self.task.evaluate()
        improved = self.validation.update(done, scores, self.selecting)
        if self.ranks.main:
            self.log.log(done, "val", scores)
            if improved:
                self.folder.save_best(self.weights(done), self.validation.best)

    def stop_early(self, done: int, progress) -> None:
        """Log what the steps since the last log trained, and say why the run stops after step ``done``."""
        if self.running.count:
            self.log_train(done, progress)
        if self.ranks.main:
            v = self.validation
            print(f"early stopping after step {done}: val_loss has not fallen below {v.best:.6g} "
                  f"(step {v.best_step}) in {v.since} validations")

    def weights(self, step: int) -> dict:
        """The checkpoint entries that rebuild the model (``models.checkpoint.load_model``)."""
        return {"task": self.cfg.task.name, "model_config": self.task.model_config(),
                "model": self.model.state_dict(), "step": step,
                "config": OmegaConf.to_container(self.cfg, resolve=True)}

    def save(self, step: int) -> None:
        """``last.pt``: the weights and everything a resumed run continues from."""
        entries = {"optimizer": self.optimizer.state_dict(), "scheduler": self.scheduler.state_dict(),
                   "validation": self.validation.state()}
        if self.trainer.amp:
            entries["scaler"] = self.scaler.state_dict()
        self.folder.save_last({**self.weights(step), **entries})

    def final_evaluation(self, stop: int, elapsed: float) -> dict[str, float]:
        """Evaluate the last weights (the best ones with ``restore_best``); write ``eval.json``."""
        folder, validation = self.folder, self.validation
        restored = self.trainer.restore_best and validation.best_step is not None and validation.best_step != stop
        if restored:
            best = load_checkpoint(folder.best)
            if best.get("step") != validation.best_step:
                raise InputError(f"{folder.best}: holds the weights of step {best.get('step')}, but the run's "
                                 f"lowest val_loss is step {validation.best_step}'s; resume the run from its last.pt")
            load_state(self.model, best["model"], folder.best, "model")
        self.model.eval()
        with torch.no_grad():
            final = self.task.evaluate(final=True)
        final = {k: float(v) for k, v in final.items()}
        if not restored and validation.update(stop, final, False):  # the last weights are a candidate too
            folder.save_best(self.weights(stop), validation.best)
        if validation.best_step is not None:
            final.update(best_step=float(validation.best_step), best_val_loss=validation.best)
        final["train_seconds"] = elapsed
        self.log.log(stop, "final", final)
        folder.write_evaluation(final)
        if restored:
            print(f"checkpoint: {folder.best} (the evaluated, best weights; {folder.last.name} holds the last ones)")
        else:
            print(f"checkpoint: {folder.last}")
        print(f"evaluation: {folder.evaluation}")
        return final
