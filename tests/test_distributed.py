"""train.py on several processes (torchrun, DistributedDataParallel on gloo), devices, sweeps, the SLURM config.

CUDA, NCCL, mixed precision and the submitit SLURM launcher cannot run on these CPU-only machines: they are
tested through their CPU paths (the same loop, gloo) and their refusals and config validation.
"""
from __future__ import annotations

import collections
import gc
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
from test_train import REPO, TINY, config, rows, weights

import tasks
import train
from base.errors import InputError
from models.checkpoint import load_checkpoint
from tasks import distributed, loop

TIMEOUT = 600


def run(args: list[str], cwd: Path, **env) -> subprocess.CompletedProcess:
    environment = {**os.environ, "OMP_NUM_THREADS": "1", **env}
    for key in ("RANK", "WORLD_SIZE", "LOCAL_RANK", "SLURM_STEP_NUM_TASKS"):
        environment.pop(key, None)
    result = subprocess.run(args, cwd=cwd, env=environment, capture_output=True, text=True, timeout=TIMEOUT)
    return result


def torchrun(cwd: Path, *overrides: str) -> subprocess.CompletedProcess:
    """``torchrun --standalone --nproc_per_node=2 train.py <TINY> <overrides>`` (train.py as users run it)."""
    result = run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                  str(REPO / "train.py"), *TINY, *overrides], cwd)
    assert result.returncode == 0, result.stderr[-3000:]
    return result


def max_difference(a: dict, b: dict) -> float:
    assert a.keys() == b.keys()
    return max(float((a[k] - b[k]).abs().max()) for k in a)


# --------------------------------------------------------------------------- two ranks = one process


@pytest.mark.slow
def test_two_ranks_train_the_one_process_weights_and_resume_after_a_stop(tmp_path):
    """Two gloo ranks, each on half of the global batch of 64, stopped after step 3 and resumed, end with the
    weights of one uninterrupted process (float tolerance: the gradient is summed in two halves), and log the
    same mean loss; only rank 0 writes (one run folder, each row once, nothing in the working folder).  The
    2-rank checkpoint also resumes on one process."""
    overrides = ("trainer.eval_every=2",)
    one = tmp_path / "one"
    loop.fit(config(*overrides), one)
    torch.manual_seed(0)
    initial = tasks.build(config()).model.state_dict()
    assert max_difference(weights(one), initial) > 1e-3  # the weights moved

    cwd = tmp_path / "cwd"
    cwd.mkdir()
    two = tmp_path / "two"
    torchrun(cwd, *overrides, "trainer.stop_after=3", f"hydra.run.dir={two}")
    assert load_checkpoint(two / "checkpoints" / "last.pt")["step"] == 3
    alone = tmp_path / "alone"
    alone.mkdir()
    (alone / "checkpoints").mkdir()
    (alone / "checkpoints" / "last.pt").write_bytes((two / "checkpoints" / "last.pt").read_bytes())
    (alone / "metrics.csv").write_bytes((two / "metrics.csv").read_bytes())
    result = torchrun(cwd, *overrides, "resume=true", f"hydra.run.dir={two}")
    assert result.stdout.count("evaluation: ") == 1  # the final evaluation: rank 0 only
    assert list(cwd.iterdir()) == []  # rank 1 wrote no run folder or log of its own
    assert max_difference(weights(two), weights(one)) < 1e-6

    logged = [(r["step"], r["split"], r["name"]) for r in rows(two)]
    assert len(logged) == len(set(logged)) and set(logged) == {(r["step"], r["split"], r["name"]) for r in rows(one)}
    for name in ("loss", "lr"):  # the loss is a mean over the batch: the ranks' mean is the global batch's
        mine = [float(r["value"]) for r in rows(two) if r["split"] == "train" and r["name"] == name]
        reference = [float(r["value"]) for r in rows(one) if r["split"] == "train" and r["name"] == name]
        assert mine == pytest.approx(reference, rel=1e-5)

    loop.fit(config(*overrides, "resume=true"), alone)  # another world size continues the same computation
    assert max_difference(weights(alone), weights(one)) < 1e-6


def test_each_rank_takes_its_slice_of_the_batch():
    """The real task's batch and a nested one: the ranks' slices are disjoint, in order, B/W rows each, and
    concatenate to the batch; values without a batch dimension pass unchanged; kinds are kept."""
    task = tasks.build(config())
    batch = task.batch(0, torch.Generator().manual_seed(0))
    slices = [distributed.split_batch(batch, rank, 4) for rank in range(4)]
    for name, value in batch.items():
        assert all(len(s[name]) == 16 for s in slices)
        assert torch.equal(torch.cat([s[name] for s in slices]), value)

    Pair = collections.namedtuple("Pair", "x scale")
    nested = {"a": torch.arange(12.0).reshape(6, 2), "b": (torch.arange(6), 5, "text"),
              "c": [Pair(torch.arange(6.0) * 2, torch.tensor(3.0))]}
    second = distributed.split_batch(nested, 1, 3)
    assert torch.equal(second["a"], torch.tensor([[4.0, 5.0], [6.0, 7.0]]))
    assert isinstance(second["b"], tuple) and torch.equal(second["b"][0], torch.tensor([2, 3]))
    assert second["b"][1:] == (5, "text")
    assert isinstance(second["c"], list) and isinstance(second["c"][0], Pair)
    assert torch.equal(second["c"][0].x, torch.tensor([4.0, 6.0])) and float(second["c"][0].scale) == 3.0

    with pytest.raises(InputError, match=r"the global batch of 6 samples does not split evenly over 4 processes: "
                                         r"choose a batch size \(task\.batch_size\) that is a multiple of 4"):
        distributed.split_batch(nested, 0, 4)
    with pytest.raises(TypeError, match=r"dim-0 sizes, expected one batch size; give the task a split_batch"):
        distributed.split_batch({"a": torch.zeros(6, 2), "b": torch.zeros(5)}, 0, 2)


def test_ranks_draw_their_own_model_randomness():
    seed, step = 3, 7
    assert loop.rank_seed(seed, step, 0) == loop.step_seeds(seed, step)[0]  # one process: unchanged
    others = [loop.rank_seed(seed, step, rank) for rank in range(1, 4)]
    assert len(set(others) | set(loop.step_seeds(seed, step))) == 5
    assert loop.rank_seed(seed, step + 1, 1) != others[0]


def test_the_parallel_wrapper_forwards_the_task_models_attributes(tmp_path):
    """Tasks call e.g. ``self.model.shift`` and ``self.model.tau_scale`` inside their loss; under DDP
    ``self.model`` is the wrapper, which must reach them while its calls still run the module."""
    class Model(torch.nn.Module):
        def __init__(self):
            super().__init__()
            self.linear = torch.nn.Linear(3, 2)
            self.register_buffer("scale", torch.tensor(2.0))
            self.marker = "mine"

        def forward(self, x):
            return self.linear(x) * self.scale

        def shift(self, x):
            return x + 1

    model = Model()
    dist.init_process_group("gloo", init_method=f"file://{tmp_path / 'store'}", rank=0, world_size=1)
    try:
        wrapped = distributed.TaskParallel(model)
        assert wrapped.marker == "mine" and float(wrapped.scale) == 2.0 and wrapped.module is model
        x = torch.ones(4, 3)
        assert torch.equal(wrapped.shift(x), x + 1) and torch.equal(wrapped(x), model(x))
        with pytest.raises(AttributeError):
            wrapped.no_such_attribute  # noqa: B018
        # The wrapper's reducer holds the process group: free it first, or tearing down the group from the
        # reducer's destructor after destroy_process_group can wait forever on gloo's threads.
        del wrapped
        gc.collect()
    finally:
        dist.destroy_process_group()


# --------------------------------------------------------------------------- devices, refusals


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present")
def test_cuda_and_mixed_precision_are_refused_without_a_gpu(tmp_path):
    assert distributed.resolve_device("auto") == torch.device("cpu")
    with pytest.raises(InputError, match=r"^trainer\.device=cuda: no CUDA device is available here"):
        loop.fit(config("trainer.device=cuda"), tmp_path / "a")
    with pytest.raises(InputError, match=r"^trainer\.amp=true: mixed precision runs on CUDA only"):
        loop.fit(config("trainer.amp=true"), tmp_path / "b")
    result = run([sys.executable, "train.py", "trainer.device=cuda", f"hydra.run.dir={tmp_path / 'c'}"], REPO)
    assert result.returncode == 2
    assert result.stderr.startswith("error: trainer.device=cuda: no CUDA device is available here")
    assert result.stderr.count("\n") == 1 and "Traceback" not in result.stderr


def test_an_unknown_device_or_key_is_one_line_and_status_2(tmp_path, capsys, monkeypatch):
    """What the trainer's schema refuses and what hydra cannot compose: one line, status 2, no run folder."""
    monkeypatch.setattr(sys, "argv", ["train.py"])
    monkeypatch.setenv("HYDRA_FULL_ERROR", "0")  # train.run sets it; restored after the test
    # hydra's "disabled" logging disables every logger that exists (disable_existing_loggers), in this process,
    # for the tests that follow: "none" configures nothing
    quiet = ["hydra/job_logging=none", "hydra/hydra_logging=none", f"hydra.run.dir={tmp_path / 'run'}"]
    device = "error: trainer: device is 'gpu', expected one of auto, cpu, cuda\n"
    for argv, message in ((["trainer.device=gpu"], device), (["trainer.speed=2"], "error: Could not override")):
        with pytest.raises(SystemExit) as stop:
            train.run([*argv, *quiet])
        err = capsys.readouterr().err
        assert stop.value.code == 2 and err.startswith(message) and err.count("\n") == 1, err
        assert not (tmp_path / "run").exists()


def test_a_cuda_run_of_a_task_that_cannot_move_is_refused(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert distributed.resolve_device("auto", 1, task_moves=False) == torch.device("cpu")
    assert distributed.resolve_device("auto", 1, task_moves=True) == torch.device("cuda", 1)
    with pytest.raises(InputError, match=r"this task cannot run on CUDA \(its Task has no to\(device\)"):
        distributed.resolve_device("cuda", 0, task_moves=False)
    with pytest.raises(InputError, match=r"the process of local rank 2 has no GPU \(2 on this machine\)"):
        distributed.resolve_device("cuda", 2)


def test_a_sweep_under_torchrun_and_untied_slurm_tasks_are_refused(monkeypatch, capsys):
    monkeypatch.setenv("WORLD_SIZE", "2")
    with pytest.raises(SystemExit) as stop:
        train.check_command_line(["-m", "seed=0,1"])
    assert stop.value.code == 2 and capsys.readouterr().err.startswith("error: -m (a hydra sweep) under torchrun")
    monkeypatch.delenv("WORLD_SIZE")
    monkeypatch.setenv("SLURM_STEP_NUM_TASKS", "4")
    with pytest.raises(InputError, match=r"4 SLURM tasks run train\.py without torchrun's environment"):
        distributed.launched_ranks()
    monkeypatch.setenv("WORLD_SIZE", "4")  # torchrun's workers inside a SLURM step
    monkeypatch.setenv("RANK", "3")
    assert distributed.launched_ranks() == distributed.Ranks(3, 4, 0)


def test_two_ranks_split_an_ensembles_members(tmp_path):
    """torchrun with task.members=3: rank 0 trains members 0 and 2, rank 1 member 1 (each alone, with its refit),
    and rank 0 writes the ensemble of the one-process run, bit for bit."""
    from test_larynx_ensemble import small_ensemble
    from test_larynx_transformer import TINY_LARYNX, tiny_config

    from tasks.members import train as train_run

    overrides = small_ensemble(tmp_path / "pairs")
    train_run(tiny_config(overrides, data=[]), tmp_path / "one")
    result = run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                  str(REPO / "train.py"), *TINY_LARYNX, *overrides, f"hydra.run.dir={tmp_path / 'two'}"], tmp_path)
    assert result.returncode == 0, result.stderr[-3000:]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["one", "pairs", "two"]  # nothing in the working folder
    for name in ("checkpoints/best.pt", "members/1/refit/checkpoints/last.pt"):
        one, two = (load_checkpoint(tmp_path / run / name)["model"] for run in ("one", "two"))
        assert max_difference(one, two) == 0, name


# --------------------------------------------------------------------------- sweeps


def test_a_seed_sweep_writes_one_run_per_job(tmp_path):
    """``python train.py -m seed=0,1``: multirun/<...>/0 and /1, job 0 the single run of seed 0."""
    sweep = tmp_path / "sweep"
    result = run([sys.executable, "train.py", "-m", "seed=0,1", *TINY, f"hydra.sweep.dir={sweep}"], REPO)
    assert result.returncode == 0, result.stderr[-3000:]
    single = tmp_path / "single"
    loop.fit(config("seed=0"), single)
    for job in ("0", "1"):
        assert (sweep / job / "eval.json").is_file() and (sweep / job / ".hydra" / "overrides.yaml").is_file()
    assert max_difference(weights(sweep / "0"), weights(single)) == 0
    assert max_difference(weights(sweep / "1"), weights(single)) > 1e-3
    assert load_checkpoint(sweep / "1" / "checkpoints" / "last.pt")["config"]["seed"] == 1


HAS_SUBMITIT = train.has_module("hydra_plugins.hydra_submitit_launcher")


@pytest.mark.skipif(not HAS_SUBMITIT, reason="the slurm extra (hydra-submitit-launcher) is not installed")
def test_the_slurm_launcher_config_composes():
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        cfg = compose("train", overrides=["hydra/launcher=slurm", "hydra.launcher.partition=gpu"],
                      return_hydra_config=True)
    launcher = cfg.hydra.launcher
    assert launcher._target_ == "hydra_plugins.hydra_submitit_launcher.submitit_launcher.SlurmLauncher"
    assert launcher.tasks_per_node == 1 and launcher.gpus_per_node == 1 and launcher.partition == "gpu"
    assert launcher.timeout_min == 240 and launcher.max_num_timeout == 0


@pytest.mark.skipif(HAS_SUBMITIT, reason="the slurm extra is installed")
def test_the_slurm_launcher_without_its_extra_names_the_install(capsys):
    with pytest.raises(SystemExit) as stop:
        train.check_command_line(["-m", "hydra/launcher=slurm", "seed=0,1"])
    assert stop.value.code == 2
    assert capsys.readouterr().err == ('error: hydra/launcher=slurm needs the hydra submitit launcher: '
                                       'pip install ".[slurm]"\n')
