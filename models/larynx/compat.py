"""Checkpoints of earlier versions: their ``model_config`` read as this version's, or refused naming the option.

Options this version removed are listed with the value at which they changed nothing (:data:`REMOVED`): a
checkpoint holding that value has weights that mean the same here, and the key is dropped.  Any other value
made a network this version cannot run: the checkpoint is refused (:class:`RemovedOptionError`).  A config of
an earlier version holds some of these keys; one saved before an option existed has no key for that option and
was trained with the value of :data:`BEFORE_OPTION`.  A config holding none of them is of this version.
"""
from __future__ import annotations

# Removed model options and the value at which each did nothing.
REMOVED = {
    "cross_window": 1,       # expression frames cross-attended to: 1 = the aligned frame only
    "period": 1,             # period of the positional encoding and of the attention bias, frames
    "feedback": False,       # the previous tau fed back into the tokens
    "use_eta": False,        # the larynx size as an input
    "input_knots": [],       # hinges of the expression weights before the input projection
    "output_norm": False,    # a LayerNorm before the head
}
# The value of an option in checkpoints saved before it existed (no key).
BEFORE_OPTION = {"input_knots": [], "output_norm": True}


class RemovedOptionError(ValueError):
    """A checkpoint trained with an option this version removed, at a value that changed the network."""


def _yaml(value) -> str:
    """A config value as written on the command line (true/false, numbers, lists)."""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_yaml(v) for v in value) + "]"
    return str(value)


def removed_options(model_config: dict) -> list[str]:
    """``model.<option>=<value>`` of every removed option ``model_config`` holds (or, being of an earlier version,
    implies by its absence: :data:`BEFORE_OPTION`) at a value that changed the network."""
    used = []
    if not any(name in model_config for name in REMOVED):
        return used  # this version's
    for name, neutral in REMOVED.items():
        value = model_config.get(name, BEFORE_OPTION.get(name, neutral))
        if (list(value) if isinstance(value, (list, tuple)) else value) != neutral:
            used.append(f"model.{name}={_yaml(value)}")
    return used


def current_config(model_config: dict) -> dict:
    """``model_config`` without the keys of removed options, each at its neutral value.

    Raises:
        RemovedOptionError: an option at another value, named (``retrain it``).
    """
    used = removed_options(model_config)
    if used:
        raise RemovedOptionError(f"trained with {', '.join(used)}, "
                                 f"{'an option' if len(used) == 1 else 'options'} this version removed; retrain it")
    return {k: v for k, v in model_config.items() if k not in REMOVED}
