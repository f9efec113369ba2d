"""Training and validation splits by recording, never by frame."""
from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from base.errors import InputError


def split_by_file(items: Sequence, val_fraction: float, seed: int, what: str = "file", fold: int = 0,
                  folds: int = 1) -> tuple[list, list]:
    """Split recordings by file: (train, validation) lists of ``items``, no item in both.

    ``round(val_fraction * len(items))`` items are held out, at least one and at most all but one;
    which ones is a permutation drawn from ``seed`` (deterministic), each list keeps the input order.
    ``fold`` of ``folds`` (the members of an ensemble): the held-out run of the permutation starts at
    ``round(fold * len(items) / folds)`` (cyclically), so fold 0 is the split of ``folds=1`` and with
    ``val_fraction = 1 / folds`` the folds' validation sets partition the items.
    ``what`` names the items in the error for fewer than two.
    """
    if len(items) < 2:
        raise InputError(f"{len(items)} {what}(s); need at least 2 to split into training and validation")
    if not 0 < val_fraction < 1:
        raise InputError(f"val_fraction must be in (0, 1), got {val_fraction}")
    if not 0 <= fold < folds:
        raise InputError(f"validation fold {fold} of {folds}: expected 0 <= fold < folds")
    count = min(len(items) - 1, max(1, int(round(val_fraction * len(items)))))
    order = np.random.default_rng(seed).permutation(len(items))
    start = int(round(fold * len(items) / folds))
    held_out = set(np.roll(order, -start)[:count].tolist())
    return ([x for i, x in enumerate(items) if i not in held_out], [x for i, x in enumerate(items) if i in held_out])
