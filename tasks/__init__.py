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
from typing import Any, Protocol

import torch
from torch import nn

TASKS = {
    "larynx_transformer": "tasks.larynx_transformer",
    "head2neck": "tasks.head2neck",
}


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
