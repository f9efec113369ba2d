"""Ensembles: a task trained as ``task.members`` networks, each from its own seed and validation fold, and one
checkpoint that averages them.

A task opts in with the fields ``members`` and ``member`` in its config and the module functions
``combine_members(checkpoints: list[dict], cfg) -> dict`` (the members' best weights -> the ensemble's
checkpoint entries: ``model_config`` and ``model``) and ``evaluate_ensemble(cfg, model) -> dict`` (the
ensemble's own validation metrics where the members share one validation set, else ``{}``).
:func:`fit_members` trains member k as a run of its own, ``task.member=k`` with :func:`member_seed`, in
``<run>/members/<k>/`` (checkpoints, ``metrics.csv``, ``eval.json``; ``resume=true`` continues each, starts
those never started, and a finished member only repeats its final evaluation; ``trainer.stop_after`` ends the
run at the member it stops), then
writes the ensemble to ``<run>/checkpoints/best.pt`` and ``last.pt`` (the same file: there is nothing to resume
in it) and ``<run>/eval.json``: every member's final evaluation, their mean, and the ensemble's own
(``ensemble_<metric>``) where the task gives one.

Refitting: a task whose members validate on folds of their own training data may define ``refits(cfg) -> bool``
(true: refit) and the config field ``task.refit_steps``.  Member k's fold then only chooses how long it trains
(its ``best_step``): the member trains again from its own seed on all the data, validation fold included, for that
many steps with the learning-rate schedule ending there and no validation (:func:`refit_config`), in
``<run>/members/<k>/refit/``; the ensemble takes those weights.  Each member's figures in ``eval.json`` stay its
fold's (the refit has no held-out data left to score on).
"""
from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path

import numpy as np
from omegaconf import DictConfig, OmegaConf

import tasks
from models.checkpoint import MODEL_BUILDERS, load_checkpoint
from tasks.distributed import launched_ranks
from tasks.run_folder import RunFolder


def member_seed(seed: int, member: int) -> int:
    """Member 0 trains from ``seed`` itself (a one-member ensemble is the single network of ``seed``); member k > 0
    from an independent 32-bit seed of ``numpy.random.SeedSequence([seed, k])``, so the members of two seeds
    share none."""
    if member == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), member]).generate_state(1, np.uint32)[0])


def trains_members(cfg: DictConfig) -> bool:
    """Whether ``cfg`` trains an ensemble (``task.members`` > 1 and no ``task.member`` chosen)."""
    return int(cfg.task.get("members", 1)) > 1 and cfg.task.get("member") is None


def member_config(cfg: DictConfig, member: int) -> DictConfig:
    """``cfg`` for member ``member`` alone: ``task.member`` set, the seed :func:`member_seed`."""
    out = copy.deepcopy(cfg)
    out.task.member = member
    out.seed = member_seed(int(cfg.seed), member)
    return out


def refit_config(cfg: DictConfig, steps: int) -> DictConfig:
    """``cfg`` (a member's) for its refit: ``task.refit_steps`` and ``trainer.max_steps`` ``steps``, no validation
    during training, no early stopping, the last weights kept."""
    out = copy.deepcopy(cfg)
    out.task.refit_steps = int(steps)
    out.trainer.max_steps = int(steps)
    out.trainer.eval_every = 0
    out.trainer.early_stopping_patience = None
    out.trainer.restore_best = False
    return out


def started(cfg: DictConfig, folder: Path) -> DictConfig:
    """``cfg`` for the run in ``folder``: with ``resume=true`` a member after the first (or a refit) that never
    saved a checkpoint there starts afresh, the others continue (the first member has nothing to continue only
    when the whole run has not: that resume stays refused)."""
    if not cfg.resume or RunFolder(folder, writer=False).last.exists():
        return cfg
    out = copy.deepcopy(cfg)
    out.resume = False
    return out


def fit_members(cfg: DictConfig, run_dir: Path, fit_one: Callable[[DictConfig, Path], dict]) -> dict[str, float]:
    """Train every member of ``cfg`` with ``fit_one`` (``tasks.loop.fit``) and write the ensemble (module
    docstring); returns the ensemble's evaluation: the members' mean of each metric, each member's under
    ``member<k>_<metric>``."""
    count, main = int(cfg.task.members), launched_ranks().main
    module = tasks.task_module(cfg.task.name)
    refits = getattr(module, "refits", lambda _: False)(cfg)
    evaluations, checkpoints = [], []
    for k in range(count):
        member_cfg = member_config(cfg, k)
        if main:
            print(f"{cfg.task.name}: member {k + 1} of {count} (seed {member_cfg.seed}, validation fold {k})",
                  flush=True)
        member_dir = run_dir / "members" / str(k)
        evaluations.append(fit_one(started(member_cfg, member_dir) if k else member_cfg, member_dir))
        if not RunFolder(member_dir, writer=False).evaluation.is_file():  # trainer.stop_after ended it
            return {}
        if refits:
            # Every rank reads rank 0's evaluation (written before the ranks left the member's process group).
            steps = int(json.loads(RunFolder(member_dir, writer=False).evaluation.read_text())["best_step"])
            if main:
                print(f"{cfg.task.name}: member {k + 1} refits on all the data for {steps} steps (its best on fold "
                      f"{k})", flush=True)
            member_dir = member_dir / "refit"
            fit_one(started(refit_config(member_cfg, steps), member_dir), member_dir)
            if not RunFolder(member_dir, writer=False).evaluation.is_file():
                return {}
            evaluations[-1]["refit_steps"] = float(steps)
        if not main:  # rank 0 alone writes (tasks.loop)
            continue
        member = RunFolder(member_dir, writer=False)
        checkpoints.append(load_checkpoint(member.best if member.best.is_file() else member.last, cfg.task.name))
    if not main:
        return {}
    folder = RunFolder(run_dir)
    combined = module.combine_members(checkpoints, cfg)
    state = {"task": cfg.task.name, **combined, "step": max(int(c.get("step", 0)) for c in checkpoints),
             "config": OmegaConf.to_container(cfg, resolve=True)}
    folder.save_last(state)
    folder.save_best(state, float(np.mean([e.get("val_loss", np.nan) for e in evaluations])))
    keys = sorted({key for e in evaluations for key in e})
    final = {key: float(np.mean([e[key] for e in evaluations if key in e])) for key in keys}
    for k, evaluation in enumerate(evaluations):
        final.update({f"member{k}_{key}": float(value) for key, value in evaluation.items()})
    model = MODEL_BUILDERS[cfg.task.name](combined["model_config"])
    model.load_state_dict(combined["model"])
    own = module.evaluate_ensemble(member_config(cfg, 0), model)
    final.update({f"ensemble_{key}": float(value) for key, value in own.items()})
    folder.write_evaluation(final)
    means = ", ".join(f"{key} {final[key]:.5g}" for key in ("rmse", "rmse_vs_ridge") if key in final)
    own = ", ".join(f"{key} {final['ensemble_' + key]:.5g}" for key in ("rmse", "rmse_vs_ridge")
                    if "ensemble_" + key in final)
    print(f"{cfg.task.name}: {count} members, each scored on its own validation, mean {means}"
          + (f"; the ensemble: {own}" if own else ""))
    print(f"checkpoint: {folder.best} (the ensemble of {run_dir / 'members'})")
    return final
