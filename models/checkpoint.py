"""Checkpoints: one ``.pt`` file holding the model, what rebuilds it, and the training state.

Layout of a checkpoint dict:
``task`` (name), ``model_config`` (dict for the model's ``build_model``, :data:`MODEL_BUILDERS`),
``model`` (state dict), ``step``, and for resuming ``optimizer``,
``scheduler``, ``config`` (the resolved run config).  Only plain containers, numbers, strings and
tensors: checkpoints are read with ``torch.load(weights_only=True)``, which runs no pickled code.
"""
from __future__ import annotations

import os
import pickle

import torch
from torch import nn

from base.errors import InputError, require_file
from base.files import atomic_path
from models import head2neck, larynx

# What rebuilds each task's model from its checkpoint's ``model_config``.
MODEL_BUILDERS = {
    "larynx_transformer": larynx.build_model,
    "head2neck": head2neck.build_model,
}


def save_checkpoint(path: str | os.PathLike, state: dict) -> None:
    """Write atomically: a crash mid-save leaves the previous checkpoint intact."""
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def load_checkpoint(path: str | os.PathLike, task: str | None = None) -> dict:
    """The checkpoint dict at ``path`` (InputError naming it when it is not one, or not of ``task``)."""
    path = require_file(path, "checkpoint")
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:  # torch's message advises weights_only=False, which would run pickled code
        raise InputError(f"{path}: not a readable checkpoint: it is not a PyTorch file, or it holds objects other "
                         f"than tensors and plain containers (checkpoints are read without running pickled code); "
                         f"expected a .pt file written by train.py") from None
    except Exception as e:  # torch raises many types for a corrupt file; its first sentence says which
        reason = " ".join(str(e).split(". ")[0].split())
        raise InputError(f"{path}: not a readable checkpoint ({type(e).__name__}: {reason})") from None
    if not isinstance(state, dict):
        raise InputError(f"{path}: holds a {type(state).__name__}, expected a checkpoint dict written by train.py")
    for key in ("task", "model_config", "model"):
        if key not in state:
            raise InputError(f"{path}: checkpoint has no '{key}' entry; expected one written by train.py")
    if task is not None and state["task"] != task:
        raise InputError(f"{path}: checkpoint of task '{state['task']}', expected '{task}'")
    return state


def load_model(path: str | os.PathLike, task: str | None = None) -> tuple[nn.Module, dict]:
    """Rebuild a trained model from a checkpoint; returns (model in eval mode, checkpoint dict)."""
    state = load_checkpoint(path, task)
    if state["task"] not in MODEL_BUILDERS:
        raise InputError(f"{path}: checkpoint of unknown task '{state['task']}', expected one of "
                         f"{', '.join(MODEL_BUILDERS)}")
    try:
        model = MODEL_BUILDERS[state["task"]](state["model_config"])
    except ValueError as e:
        raise InputError(f"{path}: checkpoint written by an incompatible version of the code: its model_config "
                         f"does not build ({e})") from None
    load_state(model, state["model"], path, "model")
    return model.eval(), state


def load_state(part, state_dict: dict, path: str | os.PathLike, name: str) -> None:
    """``part.load_state_dict(state_dict)`` (a module, optimiser or scheduler); a mismatch (missing or
    unexpected keys, other shapes: a checkpoint of an older layout) is an InputError naming ``path``."""
    try:
        part.load_state_dict(state_dict)
    except (RuntimeError, ValueError, KeyError) as e:
        reason = " ".join(str(e).split())  # torch's message spans lines
        raise InputError(f"{path}: checkpoint written by an incompatible version of the code: its {name} state "
                         f"does not load ({reason})") from None
