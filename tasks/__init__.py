"""Training tasks: the train config and the task of a name.  ``tasks.members`` drives a run (one network, or
an ensemble's members), ``tasks.loop`` trains one network; a task owns its model, data and losses.

The tasks are the names of ``models.checkpoint.MODEL_BUILDERS`` (what rebuilds each task's model from a
checkpoint), each a package or module ``tasks.<name>`` (:func:`task_module`).

A task module defines ``Task(cfg)`` with:
- ``model``: the ``nn.Module`` being trained;
- ``batch(step, generator)``: the training batch for ``step``, drawn only from
  ``generator`` (so a run is reproducible and a resumed run continues exactly);
- ``loss(batch, step) -> (loss, {name: float})``;
- ``evaluate(final=False) -> {name: float}``: validation metrics, with the
  task's baselines printed beside them when ``final``;
- ``model_config() -> dict``: what ``build_model`` needs to rebuild the model;
and a module function ``build_model(model_config) -> nn.Module``.

Optional:
- a module function ``load_data(cfg)``: the data a run loads once and its ensemble's members share (passed as
  ``Task(cfg, data)``; ``Task(cfg)`` loads its own), and the ensemble functions of ``tasks.members``;
- ``total_steps``: how many steps the task chooses for its data when ``trainer.max_steps`` is null;
- ``evaluate`` may return ``val_loss`` (lower is better): the loop then keeps ``checkpoints/best.pt``
  and can stop early and evaluate the best weights (:class:`TrainerConfig`);
- ``split_batch(batch, rank, world) -> batch``: this rank's share of the global batch under
  ``torchrun``.  Without it the loop slices every tensor of the batch (a tensor, or tuples, lists and
  dicts of them; other values are passed unchanged) on dim 0, which must be the batch dimension of
  all of them (``tasks.distributed.split_batch``);
- ``to(device)``: move the model and everything the task computes with (data tensors, the rig) to
  ``device`` once, and from then on make the tensors it creates there (``batch`` may return tensors on
  the CPU: the loop moves them).  Needed for ``trainer.device=cuda``.

Under ``torchrun`` (world size W), ``loss`` runs on each rank's slice of the global batch with
``self.model`` replaced by its ``DistributedDataParallel`` wrapper (attributes forwarded to the
module), so the task must reach the model as ``self.model`` inside ``loss``; the loss must be a mean
over the slice's samples, so that the ranks' averaged gradients are the gradient of the global batch.
"""
from __future__ import annotations

import sys
from dataclasses import dataclass, field
from typing import Any, Protocol

import torch
from torch import nn

from base.cli import REQUIRED, register_config
from models.checkpoint import MODEL_BUILDERS


@dataclass
class OptimConfig:
    """AdamW with linear warm-up then cosine decay of the learning rate (``tasks.loop.lr_factor``)."""

    lr: float = 1.0e-3
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    weight_decay: float = 0.0
    warmup_steps: int = 100
    min_lr_factor: float = 0.02  # the rate at the end of the cosine, as a fraction of lr


DEVICES = ("auto", "cpu", "cuda")


@dataclass
class TrainerConfig:
    """How long, how often, and on what the loop runs (``tasks.loop.fit``).

    Devices and processes:
    - ``device``: ``auto`` (CUDA when ``torch.cuda.is_available()``, else the CPU), ``cpu`` or ``cuda``
      (refused where there is no GPU).  Under ``torchrun`` each rank takes the GPU of its
      ``LOCAL_RANK``; the process group is NCCL on CUDA, gloo on the CPU.
    - ``amp``: mixed precision on CUDA (float16 autocast around the loss, a gradient scaler whose state
      is checkpointed); refused on the CPU.
    - ``threads``: torch threads per process.
    - ``member_workers``: processes training an ensemble's members side by side on this machine
      (``tasks.members``; 1: one after another in this process).  The results are the same bit for bit.

    Validation, early stopping and the best checkpoint: validation runs every ``eval_every`` steps
    (``task.evaluate()``, logged as ``val`` rows) except at the last step, which the final evaluation
    scores.  When the evaluation returns ``val_loss``, ``checkpoints/best.pt`` (atomic; model,
    model_config, step, val_loss, config: it loads like ``last.pt``) holds the weights of the lowest
    ``val_loss`` among the validations and the final evaluation, ``eval.json`` gets ``best_step`` and
    ``best_val_loss``, and:
    - ``early_stopping_patience``: stop after this many validations in a row without a lower
      ``val_loss`` (null = never); ``last.pt`` then records the stop, and ``resume=true`` only
      re-runs the final evaluation;
    - ``restore_best``: validate at the last step too, and run the final evaluation (``eval.json``) on
      the weights of ``best.pt`` rather than the last ones; ``last.pt`` keeps the last weights.
    Both need ``eval_every > 0`` and a task whose ``evaluate()`` returns ``val_loss`` (else InputError).
    With either set, ``eval_every`` decides what is trained, so a resumed run may not change it.
    """

    max_steps: int | None = 2000      # null: the task chooses from its data (its Task.total_steps)
    stop_after: int | None = None  # stop early (e.g. to test resume=true); the schedule still assumes max_steps
    log_every: int = 50
    eval_every: int = 500             # validation every this many steps (0 = only at the end)
    checkpoint_every: int = 500
    grad_clip: float = 1.0            # max gradient norm (0 = no clipping)
    # One thread: the models are small, and on a CPU shared with other processes a second OpenMP thread
    # stalls every parallel region (measured: 0.17 s/step on 1 thread, 0.9 s/step on 2).
    threads: int = 1
    member_workers: int = 1           # processes training an ensemble's members at once (tasks.members)
    progress: bool = True
    device: str = "auto"              # auto | cpu | cuda
    amp: bool = False                 # mixed precision (CUDA only)
    early_stopping_patience: int | None = None  # validations without a lower val_loss before stopping
    restore_best: bool = False        # final evaluation on checkpoints/best.pt's weights

    def __post_init__(self):
        if self.device not in DEVICES:
            raise ValueError(f"device is '{self.device}', expected one of {', '.join(DEVICES)}")
        if self.early_stopping_patience is not None and self.early_stopping_patience < 1:
            raise ValueError(f"early_stopping_patience is {self.early_stopping_patience}, expected at least 1 "
                             f"(or null: no early stopping)")
        if (self.early_stopping_patience is not None or self.restore_best) and self.eval_every <= 0:
            raise ValueError("early_stopping_patience and restore_best need validation during training: "
                             f"eval_every is {self.eval_every}, expected > 0")
        # max_steps 0: no step, the task's model as it starts is evaluated and saved (a calibration that trained
        # it itself, or kept a shipped model: tasks/head2neck.py).
        if self.max_steps is not None and self.max_steps < 0:
            raise ValueError(f"max_steps is {self.max_steps}, expected at least 0")
        for name in ("log_every", "checkpoint_every", "member_workers"):
            if getattr(self, name) is not None and getattr(self, name) < 1:
                raise ValueError(f"{name} is {getattr(self, name)}, expected at least 1")


@dataclass
class TrainConfig:
    """``python train.py``: the groups ``task``, ``model``, ``data`` are the chosen task's own dataclasses."""

    task: Any = REQUIRED
    model: Any = REQUIRED
    data: Any = REQUIRED
    optim: OptimConfig = field(default_factory=OptimConfig)
    trainer: TrainerConfig = field(default_factory=TrainerConfig)
    seed: int = 0
    resume: bool = False
    rig: str | None = None  # rig file from python -m data.assets for tasks that need geometry; null = built-in


register_config("train_schema", TrainConfig)
register_config("optim_schema", OptimConfig, group="optim")
register_config("trainer_schema", TrainerConfig, group="trainer")


class Task(Protocol):
    model: nn.Module

    def batch(self, step: int, generator: torch.Generator) -> Any: ...

    def loss(self, batch: Any, step: int) -> tuple[torch.Tensor, dict[str, float]]: ...

    def evaluate(self, final: bool = False) -> dict[str, float]: ...

    def model_config(self) -> dict: ...


def task_module(name: str):
    """The module of task ``name`` (``tasks.<name>``, imported below)."""
    if name not in MODEL_BUILDERS:
        raise ValueError(f"unknown task '{name}', expected one of {', '.join(MODEL_BUILDERS)}")
    return sys.modules[f"{__name__}.{name}"]


def build(cfg, data=None) -> Task:
    """The task of ``cfg``, on ``data`` (its module's ``load_data(cfg)``, shared by a run's members) when given."""
    module = task_module(cfg.task.name)
    return module.Task(cfg) if data is None else module.Task(cfg, data)


# The task modules register their own config schemas (the task, model and data groups) on import.
from tasks import head2neck, larynx_transformer  # noqa: E402,F401
