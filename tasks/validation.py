"""The validation record of a run: the lowest ``val_loss`` and its step, and early stopping.

When the task's evaluation returns ``val_loss`` (lower is better), the loop (``tasks.loop``) keeps the
weights of the lowest one in ``checkpoints/best.pt``; ``trainer.early_stopping_patience`` stops the run
after that many validations in a row without a lower one, and ``trainer.restore_best`` runs the final
evaluation on the best weights (``tasks.TrainerConfig``).
"""
from __future__ import annotations

import math

from base.errors import InputError


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
