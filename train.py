"""Training entry point: ``python train.py task=<larynx_transformer|head2neck> [overrides]``.

Composes and checks the config, then trains (``tasks.members.train``: one network through the task-agnostic
loop, ``tasks.loop.fit``, or an ensemble's members); ``tasks/<name>`` supplies the model, batches, losses and
evaluation.  Each run writes to its hydra run directory (``runs/<task>/<timestamp>`` unless
``hydra.run.dir=...``; ``-m`` sweeps write ``multirun/<task>/<timestamp>/<job number>``): ``checkpoints/last.pt``
and ``best.pt``, ``metrics.csv``, ``eval.json`` (``tasks.run_folder``); ``resume=true`` with the same
``hydra.run.dir`` continues a run.
The same config gives the same weights, resumed or not (``tasks.loop``).  Several processes
(``torchrun --nproc_per_node=N train.py ...``) train on slices of the same batches (``tasks.distributed``), or
split an ensemble's members (``tasks.members``; ``trainer.member_workers=N`` on one machine).
"""
from __future__ import annotations

import importlib.util
import os
import sys
from pathlib import Path

import hydra
from hydra.core.hydra_config import HydraConfig
from hydra.errors import HydraException
from omegaconf import DictConfig
from omegaconf.errors import OmegaConfBaseException

from base.cli import config_error, missing_keys, to_dataclass
from base.errors import InputError
from tasks.members import train
from tasks.run_folder import discard_unstarted_run


@hydra.main(version_base=None, config_path=str(Path(__file__).resolve().parent / "configs"), config_name="train")
def main(cfg: DictConfig) -> None:
    run_dir = Path(HydraConfig.get().runtime.output_dir)
    try:
        check_config(cfg)
        train(cfg, run_dir)
    except InputError as e:  # bad settings or data, a refused resume: the message, status 2, no traceback (base.cli)
        print(f"error: {e}", file=sys.stderr)
        if not cfg.resume:
            discard_unstarted_run(run_dir)
        sys.exit(2)


def run(argv: list[str]) -> None:
    """``python train.py <argv>``: hydra composes the config once and runs it (``main``); what it cannot compose
    (an unknown key, a wrong type) is one line and exit status 2, as what ``check_config`` refuses."""
    check_command_line(argv)
    sys.argv[1:] = rank_arguments(argv)
    os.environ["HYDRA_FULL_ERROR"] = "1"  # hydra raises what it cannot compose rather than printing a report
    try:
        main()
    except (HydraException, OmegaConfBaseException) as e:
        print(f"error: {config_error(e)}", file=sys.stderr)
        sys.exit(2)


def check_config(cfg: DictConfig) -> None:
    """InputError naming the settings still missing (``???``) or that the trainer's schema refuses."""
    missing = missing_keys(cfg)
    if missing:
        raise InputError(f"missing {', '.join(f'{k}=...' for k in missing)} (see configs/train.yaml)")
    to_dataclass(cfg.trainer, where="trainer")


def check_command_line(argv: list[str]) -> None:
    """Refuse, in one line with exit status 2, a sweep (``-m``) under torchrun and the SLURM launcher without its
    plugin."""
    if int(os.environ.get("WORLD_SIZE", 1)) > 1 and any(arg in ("-m", "--multirun") for arg in argv):
        print("error: -m (a hydra sweep) under torchrun: run one torchrun per sweep job, or sweep with the "
              "submitit launcher (hydra/launcher=slurm)", file=sys.stderr)
        sys.exit(2)
    if "hydra/launcher=slurm" in argv and not has_module("hydra_plugins.hydra_submitit_launcher"):
        print("error: hydra/launcher=slurm needs the hydra submitit launcher: pip install \".[slurm]\"",
              file=sys.stderr)
        sys.exit(2)


def has_module(name: str) -> bool:
    """Whether ``name`` is installed (without importing it)."""
    try:
        return importlib.util.find_spec(name) is not None
    except ModuleNotFoundError:  # its parent package is absent
        return False


def rank_arguments(argv: list[str]) -> list[str]:
    """Under torchrun, ranks other than 0 write no hydra run directory, config copy or log (they would
    each make a directory of their own clock's time): they learn rank 0's directory from it."""
    if int(os.environ.get("RANK", 0)) == 0:
        return argv
    return [*argv, "hydra.run.dir=.", "hydra.output_subdir=null", "hydra/job_logging=disabled",
            "hydra/hydra_logging=disabled"]


if __name__ == "__main__":
    run(sys.argv[1:])
