"""Task: train the expression -> larynx transformer (``models.larynx``).

Modules: :mod:`.config` (the hydra schemas of the task, its data kinds and the model sizes), :mod:`.data` (the
training and validation sequences of ``data=synthetic`` and ``data=pairs``, loaded once per run and shared by an
ensemble's members as index sets; the crop), :mod:`.baselines` (ridge
and the RMSE), :mod:`.task` (:class:`Task`: model, batches, loss, evaluation, warm start; :func:`combine_members`:
the ensemble of ``task.members`` networks, ``tasks.members``).

Data (``cfg.data``, hydra group ``data``; every sequence is resampled to ``data.fps``; tau in UV units):
- ``data=synthetic`` (:class:`SyntheticData`): ``data.synthetic_larynx`` sequences.  Validation is
  on new recordings of the training subjects (with their style) and on held-out subjects drawn from
  a *shifted* generator (``data.heldout_shift``: lags, filters, gains, swallow shapes reaching outside
  the training ranges, with the average style), reported apart as well: a person's lag or gain
  cannot be seen in their face, so on new people every model, ridge included, is left with the
  average person's;
- ``data=pairs`` (:class:`PairsData`): a folder of pair files (``data.pairs``), split into training
  and validation **by take** (``data.pairs.take_of``: the files' ``take``, else the file name
  without a trailing clip number), so clips of one recording never sit on both sides.
"""
from .baselines import fit_ridge, ridge_groups, rmse, window_features
from .config import DATA_KINDS, LarynxTaskConfig, PairsData, SyntheticData
from .data import (
    LarynxData,
    crop_for,
    load_data,
    load_sequences,
    synthetic_options,
    synthetic_training_sequences,
    with_cues,
)
from .task import Task, combine_members, evaluate_ensemble, member_weights, refits, warm_start

__all__ = [
    "DATA_KINDS", "LarynxData", "LarynxTaskConfig", "PairsData", "SyntheticData", "Task", "combine_members",
    "crop_for", "evaluate_ensemble", "fit_ridge", "load_data", "load_sequences", "member_weights", "refits",
    "ridge_groups", "rmse", "synthetic_options", "synthetic_training_sequences", "warm_start", "window_features",
    "with_cues",
]
