"""Training entry point: ``python train.py task=<larynx_transformer|head2neck> [overrides]``.

The loop is task-agnostic; ``tasks/<name>.py`` supplies the model, batches,
losses and evaluation.  Each run writes to its hydra run directory
(``runs/<task>/<timestamp>`` unless ``hydra.run.dir=...``; ``-m`` sweeps write
``multirun/<task>/<timestamp>/<job number>``):

- ``checkpoints/last.pt``: model, optimiser, scheduler, step and the resolved
  config, written atomically every ``trainer.checkpoint_every`` steps and at
  the end; ``resume=true`` with the same ``hydra.run.dir`` continues from it.
  The resumed run's config must equal the checkpoint's except for the
  run-control keys (``RUN_CONTROL_KEYS``: when to stop, log, evaluate and save,
  threads, the progress bar, the device), else InputError listing the differences;
- ``checkpoints/best.pt``: the weights of the lowest validation ``val_loss``,
  when the task's evaluation returns one (early stopping and the final
  evaluation of the best weights: ``tasks.TrainerConfig``);
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

Several processes (``torchrun --nproc_per_node=N train.py ...``, one per GPU,
or CPU processes): the same loop runs on every rank under
DistributedDataParallel (NCCL on CUDA, gloo on the CPU).  Every rank draws
the step's global batch from the same seeded generator and trains on its
``1/N`` slice (:func:`split_batch`; N must divide the batch), DDP averages
the gradients, so the update is the one-process update of the same global
batch (to float rounding; the tasks' losses are means over the batch).
Rank 0 alone writes the checkpoints, metrics and progress bar, and runs the
final evaluation; every rank validates during training (rank 0's result
decides early stopping).  The logged train metrics are the ranks' means (for
a mean over the batch, such as the loss, the one-process value; for an RMS,
the mean of the ranks' RMS).  Rank ``r > 0`` seeds torch's global generator with
:func:`rank_seed` (its own draws, e.g. dropout masks: with dropout the
ranks' masks differ from one process's, so equal weights need dropout 0).
The world size is not part of the config: a run may be resumed with another
number of processes, continuing the same computation up to float rounding.
"""
from __future__ import annotations

import dataclasses
import gc
import importlib.util
import json
import math
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import hydra
import numpy as np
import torch
import torch.distributed as dist
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig, OmegaConf
from torch.nn.parallel import DistributedDataParallel

import tasks
from base.cli import compose_config, to_dataclass
from base.errors import InputError
from base.files import write_text
from base.progress import progress_bar
from models.checkpoint import load_checkpoint, load_state, save_checkpoint

# Config keys a resumed run may change (configs/trainer/*.yaml): they steer the run, not what it computes.
RUN_CONTROL_KEYS = ("resume", "trainer.stop_after", "trainer.progress", "trainer.threads", "trainer.log_every",
                    "trainer.eval_every", "trainer.checkpoint_every", "trainer.device")
# ... except when validation chooses what is trained (early stopping, best weights): then it may not change.
SELECTION_KEYS = ("trainer.eval_every",)


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


# --------------------------------------------------------------------------- processes and devices


@dataclass(frozen=True)
class Ranks:
    """This process among the training processes (one process: rank 0 of 1).  ``local_rank`` is its
    number on its machine (torchrun's ``LOCAL_RANK``), the GPU it uses."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0


def launched_ranks() -> Ranks:
    """The ranks of an initialised process group, else of torchrun's ``RANK``, ``WORLD_SIZE``,
    ``LOCAL_RANK`` environment (absent: one process)."""
    env = os.environ
    if dist.is_available() and dist.is_initialized():
        rank = dist.get_rank()
        return Ranks(rank, dist.get_world_size(), int(env.get("LOCAL_RANK", rank)))
    if "WORLD_SIZE" not in env and int(env.get("SLURM_STEP_NUM_TASKS", 1)) > 1:
        raise InputError(f"{env['SLURM_STEP_NUM_TASKS']} SLURM tasks run train.py without torchrun's environment "
                         f"(RANK, WORLD_SIZE): each would train alone into the run directory; run one task per job "
                         f"(hydra.launcher.tasks_per_node=1) or start the processes with torchrun")
    return Ranks(int(env.get("RANK", 0)), int(env.get("WORLD_SIZE", 1)), int(env.get("LOCAL_RANK", 0)))


def resolve_device(name: str, local_rank: int = 0, task_moves: bool = True) -> torch.device:
    """``trainer.device`` (auto | cpu | cuda) as the device of the process of ``local_rank``.

    ``auto`` is CUDA when a GPU is present and the task can move there (``task_moves``: its ``Task``
    has ``to(device)``), else the CPU.  InputError for ``cuda`` without a GPU, for a task that cannot
    move, or for more processes on a machine than it has GPUs.
    """
    if name == "cpu" or (name == "auto" and not (torch.cuda.is_available() and task_moves)):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise InputError("trainer.device=cuda: no CUDA device is available here (torch.cuda.is_available() is "
                         "False); use trainer.device=auto or trainer.device=cpu")
    if not task_moves:
        raise InputError("trainer.device=cuda: this task cannot run on CUDA (its Task has no to(device), "
                         "tasks/__init__.py); use trainer.device=cpu")
    count = torch.cuda.device_count()
    if local_rank >= count:
        raise InputError(f"trainer.device={name}: the process of local rank {local_rank} has no GPU ({count} on "
                         f"this machine); start at most {count} processes per machine (torchrun --nproc_per_node)")
    return torch.device("cuda", local_rank)


def split_batch(batch, rank: int, world: int):
    """Rank ``rank``'s slice of the global ``batch`` among ``world`` ranks: rows
    ``[rank * B/world, (rank + 1) * B/world)`` on dim 0 of every tensor of at least one dimension (in a
    tensor, or tuples, lists and dicts of them, rebuilt in kind); other values are passed unchanged.

    Raises InputError when ``world`` does not divide the batch size ``B`` (equal slices make the
    ranks' mean gradients average to the global batch's), TypeError when the tensors do not share
    their dim-0 size (then the task must define ``split_batch``).
    """
    sizes: set[int] = set()

    def visit(value) -> None:
        if isinstance(value, torch.Tensor):
            if value.dim() > 0:
                sizes.add(value.shape[0])
        elif isinstance(value, dict):
            for item in value.values():
                visit(item)
        elif isinstance(value, (list, tuple)):
            for item in value:
                visit(item)

    visit(batch)
    if len(sizes) != 1:
        raise TypeError(f"cannot split the batch over {world} ranks on dim 0: its tensors have "
                        f"{sorted(sizes) or 'no'} dim-0 sizes, expected one batch size; give the task a "
                        f"split_batch(batch, rank, world) (tasks/__init__.py)")
    size = sizes.pop()
    if size % world:
        raise InputError(f"the global batch of {size} samples does not split evenly over {world} processes: "
                         f"choose a batch size (task.batch_size) that is a multiple of {world}")
    first, last = rank * size // world, (rank + 1) * size // world

    def cut(value):
        if isinstance(value, torch.Tensor):
            return value[first:last] if value.dim() > 0 else value
        if isinstance(value, dict):
            return type(value)((key, cut(item)) for key, item in value.items())
        if isinstance(value, tuple) and hasattr(value, "_fields"):  # a named tuple
            return type(value)(*(cut(item) for item in value))
        if isinstance(value, (list, tuple)):
            return type(value)(cut(item) for item in value)
        return value

    return cut(batch)


def to_device(batch, device: torch.device):
    """``batch`` (a tensor, or tuples, lists and dicts of them) with every tensor on ``device``."""
    if isinstance(batch, torch.Tensor):
        return batch.to(device, non_blocking=True)
    if isinstance(batch, dict):
        return type(batch)((key, to_device(item, device)) for key, item in batch.items())
    if isinstance(batch, tuple) and hasattr(batch, "_fields"):
        return type(batch)(*(to_device(item, device) for item in batch))
    if isinstance(batch, (list, tuple)):
        return type(batch)(to_device(item, device) for item in batch)
    return batch


class TaskParallel(DistributedDataParallel):
    """DistributedDataParallel that forwards the attributes it does not have to the wrapped module, so a
    task's ``loss`` may use ``self.model.<attribute>`` (e.g. ``shift``, ``tau_scale``) while
    ``self.model(...)`` runs through DDP's gradient synchronisation."""

    def __getattr__(self, name: str):
        try:
            return super().__getattr__(name)
        except AttributeError:
            if name == "module":
                raise
            return getattr(self.module, name)


def mean_over_ranks(values: dict[str, float], ranks: Ranks, device: torch.device) -> dict[str, float]:
    """The mean of each value over the ranks (every rank passes the same keys in the same order)."""
    if ranks.world == 1 or not values:
        return values
    total = torch.tensor(list(values.values()), dtype=torch.float64, device=device)
    dist.all_reduce(total)
    return dict(zip(values, (total / ranks.world).tolist()))


def from_rank0(value, ranks: Ranks):
    """Rank 0's ``value`` on every rank (a picklable object)."""
    if ranks.world == 1:
        return value
    box = [value]
    dist.broadcast_object_list(box, src=0)
    return box[0]


# --------------------------------------------------------------------------- validation


class Validation:
    """The validation ``val_loss`` record: the lowest so far and its step, the validations since, and
    whether early stopping ended the run (checkpointed with ``last.pt`` as :meth:`state`)."""

    def __init__(self, patience: int | None, state: dict | None = None):
        self.patience = patience
        state = state or {}
        self.best: float = state.get("best", math.inf)
        self.best_step: int | None = state.get("best_step")
        self.since: int = state.get("since", 0)
        self.stopped: bool = state.get("stopped", False)

    def state(self) -> dict:
        return {"best": self.best, "best_step": self.best_step, "since": self.since, "stopped": self.stopped}

    def update(self, step: int, metrics: dict[str, float], needed: bool) -> bool:
        """Record the validation of ``step``; True when its ``val_loss`` is the lowest so far.  InputError
        when ``val_loss`` is absent but ``needed`` (early stopping or restore_best)."""
        if "val_loss" not in metrics:
            if needed:
                raise InputError(f"trainer.early_stopping_patience / trainer.restore_best need a val_loss from the "
                                 f"task's evaluation, which returned {', '.join(metrics) or 'nothing'}; unset them")
            return False
        loss = float(metrics["val_loss"])
        if loss < self.best:
            self.best, self.best_step, self.since = loss, step, 0
            return True
        self.since += 1
        return False

    def patience_spent(self) -> bool:
        return self.patience is not None and self.since >= self.patience


# --------------------------------------------------------------------------- the loop


def fit(cfg: DictConfig, run_dir: Path) -> dict[str, float]:
    """Train the task of ``cfg`` in ``run_dir``; returns the final evaluation (on rank 0; ``{}`` on the
    other ranks and when ``trainer.stop_after`` ends the run)."""
    trainer = to_dataclass(cfg.trainer, where="trainer")
    ranks = launched_ranks()
    if trainer.threads:
        torch.set_num_threads(int(trainer.threads))
    task_moves = hasattr(tasks.task_module(cfg.task.name).Task, "to")
    device = resolve_device(trainer.device, ranks.local_rank, task_moves)
    if trainer.device == "auto" and device.type == "cpu" and torch.cuda.is_available() and ranks.main:
        print(f"note: task {cfg.task.name} cannot run on CUDA (its Task has no to(device)): training on the CPU")
    if trainer.amp and device.type != "cuda":
        raise InputError(f"trainer.amp=true: mixed precision runs on CUDA only, and this run is on the CPU "
                         f"(trainer.device={trainer.device}); set trainer.amp=false")
    started_group = False
    if ranks.world > 1 and not dist.is_initialized():
        if device.type == "cuda":
            torch.cuda.set_device(device)
        dist.init_process_group("nccl" if device.type == "cuda" else "gloo")
        started_group = True
    try:
        final = _fit(cfg, trainer, Path(from_rank0(str(run_dir), ranks)), ranks, device)
        if started_group:  # a rank that tore gloo down while rank 0 still wrote its checkpoint aborted at exit
            dist.barrier()
        return final
    finally:
        if started_group:  # _fit's DDP wrapper holds the group in its reducer, in reference cycles: free it first
            gc.collect()
            dist.destroy_process_group()


def _fit(cfg: DictConfig, trainer, run_dir: Path, ranks: Ranks, device: torch.device) -> dict[str, float]:
    main = ranks.main
    if main:
        run_dir.mkdir(parents=True, exist_ok=True)
    checkpoint_path = run_dir / "checkpoints" / "last.pt"
    best_path = run_dir / "checkpoints" / "best.pt"
    state = None
    if not cfg.resume and checkpoint_path.exists():
        raise InputError(f"{checkpoint_path}: this run directory already holds a run; resume=true continues it, "
                         f"or choose another hydra.run.dir")
    if cfg.resume:
        if not checkpoint_path.exists():
            raise InputError(f"{checkpoint_path}: not found, so resume=true has nothing to continue; pass "
                             f"hydra.run.dir=<the run's directory>")
        state = load_checkpoint(checkpoint_path)
        check_resumable(state, cfg, checkpoint_path)
    torch.manual_seed(cfg.seed)
    task = tasks.build(cfg)
    if trainer.max_steps is None:  # the task's choice for its data
        if getattr(task, "total_steps", None) is None:
            raise InputError(f"trainer.max_steps=null: task {cfg.task.name} does not choose its length; "
                             f"set trainer.max_steps")
        trainer = dataclasses.replace(trainer, max_steps=int(task.total_steps))
        if main:
            print(f"{cfg.task.name}: {trainer.max_steps} training steps for these data (trainer.max_steps=null)")
    model = task.model
    if device.type != "cpu":
        task.to(device)
        model = task.model
    optimizer = torch.optim.AdamW(
        model.parameters(), lr=cfg.optim.lr, betas=tuple(cfg.optim.betas), weight_decay=cfg.optim.weight_decay
    )
    scheduler = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: lr_factor(s, cfg.optim.warmup_steps, trainer.max_steps, cfg.optim.min_lr_factor)
    )
    scaler = torch.amp.GradScaler(device.type, enabled=trainer.amp)
    start = 0
    log = MetricsLog(run_dir / "metrics.csv") if main else None
    if state is not None:
        for name, part in (("model", model), ("optimizer", optimizer), ("scheduler", scheduler)):
            load_state(part, state[name], checkpoint_path, name)
        if trainer.amp and "scaler" in state:
            load_state(scaler, state["scaler"], checkpoint_path, "scaler")
        start = int(state["step"])
        if main:
            log.truncate(start)
    validation = Validation(trainer.early_stopping_patience, state.get("validation") if state else None)
    selecting = trainer.early_stopping_patience is not None or trainer.restore_best
    # DDP after the resumed weights are loaded (it starts every rank from rank 0's parameters).
    parallel = None
    if ranks.world > 1:
        parallel = TaskParallel(model, device_ids=[device.index] if device.type == "cuda" else None,
                                forward_sync_buffers=False)  # the models' buffers are constants

    def save(step: int) -> None:
        entries = {"optimizer": optimizer.state_dict(), "scheduler": scheduler.state_dict(),
                   "validation": validation.state()}
        if trainer.amp:
            entries["scaler"] = scaler.state_dict()
        save_checkpoint(checkpoint_path, {**weights(step), **entries})

    def weights(step: int) -> dict:
        return {"task": cfg.task.name, "model_config": task.model_config(), "model": model.state_dict(),
                "step": step, "config": OmegaConf.to_container(cfg, resolve=True)}

    stop = trainer.max_steps if trainer.stop_after is None else min(trainer.max_steps, trainer.stop_after)
    if validation.stopped:  # resuming a run that stopped early: only the final evaluation is left
        stop = start
    progress = progress_bar(range(start, stop), initial=start, total=stop, desc=cfg.task.name, unit="step",
                            disable=not (trainer.progress and main))
    running: dict[str, float] = {}
    count = 0

    def log_train(done: int) -> None:
        """Log the mean of the train metrics since the last log (over the steps and the ranks)."""
        nonlocal running, count
        averaged = mean_over_ranks({k: v / count for k, v in running.items()}, ranks, device)
        if main:
            log.log(done, "train", {**averaged, "lr": scheduler.get_last_lr()[0]})
            progress.set_postfix({k: f"{v:.4g}" for k, v in list(averaged.items())[:3]})
        running, count = {}, 0

    started = time.perf_counter()
    for step in progress:
        global_seed, batch_seed = step_seeds(int(cfg.seed), step)
        torch.manual_seed(global_seed if ranks.rank == 0 else rank_seed(int(cfg.seed), step, ranks.rank))
        batch = task.batch(step, torch.Generator().manual_seed(batch_seed))
        if ranks.world > 1:
            split = getattr(task, "split_batch", split_batch)
            batch = split(batch, ranks.rank, ranks.world)
        if device.type != "cpu":
            batch = to_device(batch, device)
        model.train()
        if parallel is not None:
            task.model = parallel  # the loss's forward passes go through DDP
        try:
            with torch.autocast(device.type, dtype=torch.float16, enabled=trainer.amp):
                loss, metrics = task.loss(batch, step)
        finally:
            task.model = model
        optimizer.zero_grad(set_to_none=True)
        scaler.scale(loss).backward()
        if trainer.grad_clip:
            scaler.unscale_(optimizer)
            torch.nn.utils.clip_grad_norm_(model.parameters(), trainer.grad_clip)
        scaler.step(optimizer)
        scaler.update()
        scheduler.step()
        for k, v in metrics.items():
            running[k] = running.get(k, 0.0) + float(v)
        count += 1
        done = step + 1
        if done % trainer.log_every == 0 or done == stop:
            log_train(done)
        # At the last step the final evaluation follows; validate there too only to choose between the last
        # and the best weights (restore_best).
        last = done == trainer.max_steps
        if trainer.restore_best if last else bool(trainer.eval_every) and done % trainer.eval_every == 0:
            model.eval()
            with torch.no_grad():
                scores = task.evaluate()
            improved = validation.update(done, scores, selecting)
            if main:
                log.log(done, "val", scores)
                if improved:
                    save_checkpoint(best_path, {**weights(done), "val_loss": validation.best})
            if from_rank0(validation.patience_spent(), ranks) and not last:
                validation.stopped, stop = True, done
                if count:
                    log_train(done)
                if main:
                    print(f"early stopping after step {done}: val_loss has not fallen below {validation.best:.6g} "
                          f"(step {validation.best_step}) in {validation.since} validations")
        if main and (done % trainer.checkpoint_every == 0 or done == stop):
            save(done)
        if validation.stopped:
            break
    elapsed = time.perf_counter() - started
    if stop < trainer.max_steps and not validation.stopped:
        if main:
            print(f"stopped after step {stop} of {trainer.max_steps} (trainer.stop_after); resume=true continues")
        return {}
    if not main:
        return {}
    restored = trainer.restore_best and validation.best_step is not None and validation.best_step != stop
    if restored:
        best = load_checkpoint(best_path)
        if best.get("step") != validation.best_step:
            raise InputError(f"{best_path}: holds the weights of step {best.get('step')}, but the run's lowest "
                             f"val_loss is step {validation.best_step}'s; resume the run from its last.pt")
        load_state(model, best["model"], best_path, "model")
    model.eval()
    with torch.no_grad():
        final = task.evaluate(final=True)
    final = {k: float(v) for k, v in final.items()}
    if not restored and validation.update(stop, final, False):  # the last weights are a candidate too
        save_checkpoint(best_path, {**weights(stop), "val_loss": validation.best})
    if validation.best_step is not None:
        final.update(best_step=float(validation.best_step), best_val_loss=validation.best)
    final["train_seconds"] = elapsed
    log.log(stop, "final", final)
    write_text(run_dir / "eval.json", json.dumps(final, indent=2) + "\n")
    if restored:
        print(f"checkpoint: {best_path} (the evaluated, best weights; {checkpoint_path.name} holds the last ones)")
    else:
        print(f"checkpoint: {checkpoint_path}")
    print(f"evaluation: {run_dir / 'eval.json'}")
    return final


@hydra.main(version_base=None, config_path="configs", config_name="train")
def main(cfg: DictConfig) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        fit(cfg, run_dir)
    except InputError as e:  # bad data or a refused resume: the message, status 2, no traceback (base.cli)
        print(f"error: {e}", file=sys.stderr)
        if not cfg.resume:
            discard_unstarted_run(run_dir)
        sys.exit(2)


def discard_unstarted_run(run_dir: Path) -> None:
    """Remove what hydra wrote into ``run_dir`` (``.hydra/``, the job's log) for a run refused before it saved
    anything, the folder if that leaves it empty, and the folders above it inside the working directory that
    are left empty (``runs/<task>/`` of a first run): a refused run leaves no half-made run folder."""
    if (run_dir / "checkpoints").exists() or not run_dir.is_dir():
        return
    shutil.rmtree(run_dir / ".hydra", ignore_errors=True)
    for log_file in run_dir.glob("*.log"):
        log_file.unlink(missing_ok=True)
    run_dir, cwd = run_dir.resolve(), Path.cwd().resolve()
    above = [folder for folder in run_dir.parents if cwd in folder.parents]  # inside the working directory
    for folder in [run_dir, *above]:
        if any(folder.iterdir()):
            break
        folder.rmdir()


def check_command_line(argv: list[str]) -> None:
    """Compose the config once before hydra runs it, so an unknown key, a wrong type or a missing value is
    one line and exit status 2 (base.cli) rather than hydra's report.  Sweeps (``-m``) and hydra's own
    flags and keys are left to hydra; a sweep under torchrun is refused."""
    if int(os.environ.get("WORLD_SIZE", 1)) > 1 and any(arg in ("-m", "--multirun") for arg in argv):
        print("error: -m (a hydra sweep) under torchrun: run one torchrun per sweep job, or sweep with the "
              "submitit launcher (hydra/launcher=slurm)", file=sys.stderr)
        sys.exit(2)
    if "hydra/launcher=slurm" in argv and not has_module("hydra_plugins.hydra_submitit_launcher"):
        print("error: hydra/launcher=slurm needs the hydra submitit launcher: pip install \".[slurm]\"",
              file=sys.stderr)
        sys.exit(2)
    if any(arg.startswith("-") for arg in argv):
        return
    try:
        cfg = compose_config("train", [arg for arg in argv if not arg.startswith(("hydra.", "hydra/", "+hydra"))])
        to_dataclass(cfg.trainer, where="trainer")
    except InputError as e:
        print(f"error: {e}", file=sys.stderr)
        sys.exit(2)


def has_module(name: str) -> bool:
    """Whether ``name`` is installed (without importing it)."""
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # its parent package is absent
        return False


def rank_arguments(argv: list[str]) -> list[str]:
    """Under torchrun, ranks other than 0 write no hydra run directory, config copy or log (they would
    each make a directory of their own clock's time): they learn rank 0's directory from it."""
    if int(os.environ.get("RANK", 0)) == 0:
        return argv
    return [*argv, "hydra.run.dir=.", "hydra.output_subdir=null", "hydra/job_logging=disabled",
            "hydra/hydra_logging=disabled"]


if __name__ == "__main__":
    check_command_line(sys.argv[1:])
    sys.argv[1:] = rank_arguments(sys.argv[1:])
    main()
