"""Training tasks.  ``train.py`` owns the loop; a task owns its model, data and losses.

A task module defines ``Task(cfg)`` with:
- ``model``: the ``nn.Module`` being trained;
- ``batch(step, generator)``: the training batch for ``step``, drawn only from
  ``generator`` (so a run is reproducible and a resumed run continues exactly);
- ``loss(batch, step) -> (loss, {name: float})``;
- ``evaluate(final=False) -> {name: float}``: validation metrics, with the
  task's baselines printed beside them when ``final``;
- ``model_config() -> dict``: what ``build_model`` needs to rebuild the model;
and a module function ``build_model(model_config) -> nn.Module``.
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Any, Optional, Protocol

import torch
from torch import nn

from data.cli import REQUIRED, register_config

TASKS = {
    "larynx_transformer": "tasks.larynx_transformer",
    "head2neck": "tasks.head2neck",
}


@dataclass
class OptimConfig:
    """AdamW with linear warm-up then cosine decay of the learning rate (``train.lr_factor``)."""

    lr: float = 1.0e-3
    betas: list[float] = field(default_factory=lambda: [0.9, 0.999])
    weight_decay: float = 0.0
    warmup_steps: int = 100
    min_lr_factor: float = 0.02  # the rate at the end of the cosine, as a fraction of lr


@dataclass
class TrainerConfig:
    """How long, how often, and on what the loop runs (``train.fit``)."""

    max_steps: int = 2000
    stop_after: Optional[int] = None  # stop early (e.g. to test resume=true); the schedule still assumes max_steps
    log_every: int = 50
    eval_every: int = 500             # validation every this many steps (0 = only at the end)
    checkpoint_every: int = 500
    grad_clip: float = 1.0            # max gradient norm (0 = no clipping)
    # One thread: the models are small, and on a CPU shared with other processes a second OpenMP thread
    # stalls every parallel region (measured: 0.17 s/step on 1 thread, 0.9 s/step on 2).
    threads: int = 1
    progress: bool = True


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
    rig: Optional[str] = None  # rig file from python -m data.assets for tasks that need geometry; null = built-in


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
    if name not in TASKS:
        raise ValueError(f"unknown task '{name}', expected one of {', '.join(TASKS)}")
    return importlib.import_module(TASKS[name])


def build(cfg) -> Task:
    return task_module(cfg.task.name).Task(cfg)


# The task modules register their own config schemas (the task, model and data groups) on import.
from tasks import head2neck, larynx_transformer  # noqa: E402,F401
