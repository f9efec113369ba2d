"""A training run: one network (``tasks.loop.fit``), or an ensemble of ``task.members`` networks, each from its own
seed and validation fold, and one checkpoint that averages them.

:func:`train` is the run of ``python train.py``.  A task opts in to ensembles with the config fields ``members``
and ``member`` and the module functions ``load_data(cfg)`` (the data, loaded once per run and shared by the
members: each trains and validates on index sets of it, its fold), ``combine_members(checkpoints, cfg)`` (the
members' best weights -> the ensemble's ``nn.Module``) and ``evaluate_ensemble(cfg, model, data)`` (the
ensemble's own validation metrics where the members share one validation set, else ``{}``).  What the members
compute once per run goes in ``data.baselines`` (a dict; member processes send theirs back).

Member k trains as a run of its own (:func:`member_config`: ``task.member=k``, the seed :func:`member_seed`) in
``<run>/members/<k>/`` (checkpoints, ``metrics.csv``, ``eval.json``; ``resume=true`` continues each, starts those
never started (a run whose first member never started has nothing to resume: refused), and a finished member only
repeats its final evaluation; ``trainer.stop_after`` stops every member
there and writes no ensemble), then the ensemble goes to ``<run>/checkpoints/best.pt`` and ``last.pt`` (the same
file: there is nothing to resume in it) and ``<run>/eval.json``: every member's final evaluation, their mean, and
the ensemble's own (``ensemble_<metric>``) where the task gives one.

Refitting: a task whose members validate on folds of their own training data may define ``refits(cfg) -> bool``
(true: refit) and the config field ``task.refit_steps``.  Member k's fold then only chooses how long it trains
(its ``best_step``): the member trains again from its own seed on all the data, validation fold included, for that
many steps with the learning-rate schedule ending there and no validation (:func:`refit_config`), in
``<run>/members/<k>/refit/``; the ensemble takes those weights.  Each member's figures in ``eval.json`` stay its
fold's (the refit has no held-out data left to score on).

Where the members train (the same weights bit for bit every way: each run is seeded and alone in its process):
- ``trainer.member_workers=1``: one after another in this process;
- ``trainer.member_workers=N``: N processes of this machine (forked on Linux, else spawned and given the data
  once), handed the members' runs and refits as they free up;
- under ``torchrun`` with ``task.members`` > 1: the ranks split the members (rank r trains members r, r + W, ...,
  each alone, no DDP) and rank 0 writes the ensemble once every rank has finished; with one member the ranks train
  it together under DDP (``tasks.loop``);
- ``task.member=k``: member k alone (and its refit) in the run folder: one job of a sweep over the members
  (``-m task.member=0,1,...`` with ``hydra.sweep.subdir=members/${task.member}``, e.g. one SLURM job each); a
  run with ``resume=true`` in the sweep's folder then writes the ensemble (docs/training.md).
"""
from __future__ import annotations

import copy
import datetime
import json
import sys
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
from omegaconf import DictConfig, OmegaConf

import tasks
from models.checkpoint import load_checkpoint
from tasks.distributed import Ranks, launched_ranks
from tasks.loop import fit
from tasks.run_folder import RunFolder

# Member processes are forks of the run's where the system has them (Linux: no second import of torch, the data
# shared as it is; the run's process has computed nothing with torch's thread pool yet), else spawned.
START_METHOD = "fork" if sys.platform == "linux" else "spawn"
# A rank that trains its members alone waits for the others' at the end: as long as their members take.
MEMBER_WAIT = datetime.timedelta(days=7)


def member_seed(seed: int, member: int) -> int:
    """Member 0 trains from ``seed`` itself (a one-member ensemble is the single network of ``seed``); member k > 0
    from an independent 32-bit seed of ``numpy.random.SeedSequence([seed, k])``, so the members of two seeds
    share none."""
    if member == 0:
        return int(seed)
    return int(np.random.SeedSequence([int(seed), member]).generate_state(1, np.uint32)[0])


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
    """``cfg`` for the run in ``folder``: with ``resume=true`` a run that never saved a checkpoint there starts
    afresh, the others continue."""
    if not cfg.resume or RunFolder(folder, writer=False).last.exists():
        return cfg
    out = copy.deepcopy(cfg)
    out.resume = False
    return out


def train(cfg: DictConfig, run_dir: Path) -> dict[str, float]:
    """Run ``cfg`` in ``run_dir`` (module docstring); returns the final evaluation (the ensemble's: the members'
    mean of each metric, each member's under ``member<k>_<metric>``) on the writing process, else ``{}``."""
    module = tasks.task_module(cfg.task.name)
    count = int(cfg.task.get("members", 1))
    if count == 1:
        return fit(cfg, run_dir)
    first = int(cfg.task.get("member") or 0)
    first_dir = run_dir if cfg.task.get("member") is not None else member_folders(run_dir, [0])[0]
    if launched_ranks().main:  # the run's first member has nothing to resume: refused before the data load
        RunFolder(first_dir, writer=False).resume_state(member_config(cfg, first))
    data = module.load_data(cfg)
    refits = getattr(module, "refits", lambda _: False)(cfg)
    if cfg.task.get("member") is not None:  # one member alone, in the run folder itself
        member = int(cfg.task.member)
        finished = run_members(cfg, {member: run_dir}, data, refits, Ranks())
        return json.loads(RunFolder(run_dir, writer=False).evaluation.read_text()) if finished else {}
    ranks = launched_ranks()
    if ranks.world == 1:
        if not run_members(cfg, member_folders(run_dir, range(count)), data, refits, ranks):
            return {}
        return write_ensemble(cfg, run_dir, data, module)
    # torchrun: rank r trains members r, r + W, ... alone (no DDP), then rank 0 writes the ensemble.
    dist.init_process_group("gloo", timeout=MEMBER_WAIT)
    try:
        box = [str(run_dir)]
        dist.broadcast_object_list(box, src=0)  # the ranks after 0 run in hydra.run.dir=. (train.py)
        run_dir = Path(box[0])
        own = Ranks(0, 1, ranks.local_rank)
        finished = run_members(cfg, member_folders(run_dir, range(ranks.rank, count, ranks.world)), data, refits, own)
        finished = all(f for f in gather(finished))
    finally:
        dist.destroy_process_group()
    if not (ranks.main and finished):
        return {}
    return write_ensemble(cfg, run_dir, data, module)


def gather(value) -> list:
    """Every rank's ``value`` (a picklable object), on every rank."""
    out = [None] * dist.get_world_size()
    dist.all_gather_object(out, value)
    return out


def member_folders(run_dir: Path, members) -> dict[int, Path]:
    return {k: run_dir / "members" / str(k) for k in members}


def run_members(cfg: DictConfig, folders: dict[int, Path], data, refits: bool, ranks: Ranks) -> bool:
    """Train the members ``folders`` names (member -> its folder), and each one's refit once its fold has chosen
    the length, on ``trainer.member_workers`` processes; whether every one finished (``trainer.stop_after``)."""
    workers = min(int(cfg.trainer.member_workers), len(folders))
    if workers > 1:
        pool = ProcessPoolExecutor(workers, mp_context=get_context(START_METHOD), initializer=start_worker,
                                   initargs=(data, int(cfg.trainer.threads), ranks))
        cfg = copy.deepcopy(cfg)
        cfg.trainer.progress = False  # several bars on one terminal
    else:
        pool = InProcess(data, ranks)
    count, finished = int(cfg.task.members), True
    with pool:
        jobs: dict[Future, tuple[int, DictConfig | None]] = {}
        for k, folder in folders.items():
            member_cfg = member_config(cfg, k)
            print(f"{cfg.task.name}: member {k + 1} of {count} (seed {member_cfg.seed}, validation fold {k})",
                  flush=True)
            jobs[pool.submit(fit_in_worker, started(member_cfg, folder), folder)] = (k, member_cfg)
        while jobs:
            done, _ = wait(jobs, return_when=FIRST_COMPLETED)
            for job in [job for job in jobs if job in done]:  # in the order they were handed out
                k, member_cfg = jobs.pop(job)
                baselines = job.result()
                if hasattr(data, "baselines"):
                    data.baselines.update(baselines)
                folder = folders[k] if member_cfg is not None else folders[k] / "refit"
                if not RunFolder(folder, writer=False).evaluation.is_file():  # trainer.stop_after ended it
                    finished = False
                    continue
                if member_cfg is None or not refits:
                    continue
                steps = int(json.loads(RunFolder(folder, writer=False).evaluation.read_text())["best_step"])
                print(f"{cfg.task.name}: member {k + 1} refits on all the data for {steps} steps (its best on fold "
                      f"{k})", flush=True)
                refit = folders[k] / "refit"
                jobs[pool.submit(fit_in_worker, started(refit_config(member_cfg, steps), refit), refit)] = (k, None)
    return finished


# In a member process: the run's data (given once, start_worker) and that the process trains alone.
WORKER: dict = {}


def start_worker(data, threads: int, ranks: Ranks) -> None:
    torch.set_num_threads(threads)
    WORKER.update(data=data, ranks=ranks)


def fit_in_worker(cfg: DictConfig, folder: Path) -> dict:
    """``tasks.loop.fit`` of ``cfg`` in ``folder`` on the worker's data; returns what it added to
    ``data.baselines``."""
    data = WORKER["data"]
    fit(cfg, folder, data, WORKER["ranks"])
    return getattr(data, "baselines", {})


class InProcess:
    """The executor of ``trainer.member_workers=1``: each job runs in this process as it is submitted."""

    def __init__(self, data, ranks: Ranks):
        self.state = {"data": data, "ranks": ranks}

    def submit(self, fn, *args) -> Future:
        future: Future = Future()
        saved = dict(WORKER)
        WORKER.update(self.state)
        try:
            future.set_result(fn(*args))
        except Exception as e:  # noqa: BLE001  (re-raised by result(), as a process pool does)
            future.set_exception(e)
        finally:
            WORKER.clear()
            WORKER.update(saved)
        return future

    def __enter__(self) -> InProcess:
        return self

    def __exit__(self, *exc) -> None:
        return None


def write_ensemble(cfg: DictConfig, run_dir: Path, data, module) -> dict[str, float]:
    """Average the finished members of ``run_dir`` (their refits' weights where they refit) into the run's
    checkpoint, score it where the task can (``evaluate_ensemble``) and write ``eval.json``."""
    count = int(cfg.task.members)
    evaluations, checkpoints = [], []
    for folder in member_folders(run_dir, range(count)).values():
        evaluation = json.loads(RunFolder(folder, writer=False).evaluation.read_text())
        refit = RunFolder(folder / "refit", writer=False)
        if refit.evaluation.is_file():
            evaluation["refit_steps"] = float(evaluation["best_step"])
            folder = refit.path
        evaluations.append(evaluation)
        member = RunFolder(folder, writer=False)
        checkpoints.append(load_checkpoint(member.best if member.best.is_file() else member.last, cfg.task.name))
    ensemble = module.combine_members(checkpoints, cfg)
    state = {"task": cfg.task.name, "model_config": ensemble.config, "model": ensemble.state_dict(),
             "step": max(int(c.get("step", 0)) for c in checkpoints),
             "config": OmegaConf.to_container(cfg, resolve=True)}
    folder = RunFolder(run_dir)
    folder.save_last(state)
    folder.save_best(state, float(np.mean([e.get("val_loss", np.nan) for e in evaluations])))
    keys = sorted({key for e in evaluations for key in e})
    final = {key: float(np.mean([e[key] for e in evaluations if key in e])) for key in keys}
    for k, evaluation in enumerate(evaluations):
        final.update({f"member{k}_{key}": float(value) for key, value in evaluation.items()})
    own = module.evaluate_ensemble(cfg, ensemble, data)
    final.update({f"ensemble_{key}": float(value) for key, value in own.items()})
    folder.write_evaluation(final)
    means = ", ".join(f"{key} {final[key]:.5g}" for key in ("rmse", "rmse_vs_ridge") if key in final)
    own = ", ".join(f"{key} {final['ensemble_' + key]:.5g}" for key in ("rmse", "rmse_vs_ridge")
                    if "ensemble_" + key in final)
    print(f"{cfg.task.name}: {count} members, each scored on its own validation, mean {means}"
          + (f"; the ensemble: {own}" if own else ""))
    print(f"checkpoint: {folder.best} (the ensemble of {run_dir / 'members'})")
    return final
