"""The training loop (train.py) and checkpoints (models/checkpoint.py): resume checks, metrics, seeds, loading.

Runs are tiny head2neck trainings (a few steps on a few synthetic sequences): the loop is task-agnostic.
"""
from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import train
from data.errors import InputError
from models.checkpoint import load_checkpoint, load_model, save_checkpoint

REPO = Path(__file__).resolve().parents[1]
MAX_STEPS = 6


def config(*overrides):
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("train", overrides=[
            "task=head2neck", "model.hidden=[16]", "data.train_sequences=8", "data.val_sequences=2",
            "data.seconds=1.0", "task.batch_size=64", f"trainer.max_steps={MAX_STEPS}", "trainer.eval_every=0",
            "trainer.log_every=1", "trainer.checkpoint_every=2", "trainer.progress=false", "trainer.threads=1",
            "optim.warmup_steps=2", *overrides])


def rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def weights(run_dir: Path) -> dict:
    return load_checkpoint(run_dir / "checkpoints" / "last.pt")["model"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run (logging every third step only: run control, not what is computed)."""
    run_dir = tmp_path_factory.mktemp("reference")
    train.fit(config("trainer.log_every=3"), run_dir)
    return run_dir


def test_resume_refuses_another_config_and_accepts_other_run_control(tmp_path, reference):
    run_dir = tmp_path / "run"
    train.fit(config("trainer.stop_after=3"), run_dir)
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"] == 3
    lr = config().optim.lr
    assert lr != 0.01
    with pytest.raises(InputError, match=r"last\.pt: resume=true with a config that differs from the checkpoint's "
                                         + re.escape(f"(optim.lr: {lr!r} -> 0.01); only resume, trainer.stop_after")):
        train.fit(config("resume=true", "optim.lr=0.01"), run_dir)
    with pytest.raises(InputError, match=r"data\.seed: 1 -> 5; model\.hidden: \[16\] -> \[32\]"):
        train.fit(config("resume=true", "data.seed=5", "model.hidden=[32]"), run_dir)
    with pytest.raises(InputError, match="checkpoint of task 'head2neck', but resume=true runs task 'larynx_transformer'"):
        train.fit(compose_larynx("resume=true"), run_dir)
    # stop_after and log_every differ from the first part: allowed, and the weights are the uninterrupted run's
    train.fit(config("resume=true", "trainer.log_every=2"), run_dir)
    assert (run_dir / "eval.json").is_file()
    resumed, uninterrupted = weights(run_dir), weights(reference)
    assert resumed.keys() == uninterrupted.keys()
    assert all(torch.equal(resumed[k], uninterrupted[k]) for k in resumed)


def compose_larynx(*overrides):
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("train", overrides=["task=larynx_transformer", "trainer.progress=false", *overrides])


def test_resume_drops_the_metrics_logged_after_the_checkpoint(tmp_path, monkeypatch):
    from tasks.head2neck import Task

    whole = tmp_path / "whole"
    train.fit(config(), whole)
    loss = Task.loss

    def interrupted(self, batch, step):
        if step == MAX_STEPS - 1:
            raise RuntimeError("interrupted")
        return loss(self, batch, step)

    run_dir = tmp_path / "run"
    monkeypatch.setattr(Task, "loss", interrupted)
    with pytest.raises(RuntimeError, match="interrupted"):
        train.fit(config(), run_dir)
    monkeypatch.undo()
    checkpoint_step = load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"]
    assert checkpoint_step == MAX_STEPS - 2 and {int(r["step"]) for r in rows(run_dir)} == set(range(1, MAX_STEPS))
    train.fit(config("resume=true"), run_dir)
    resumed = rows(run_dir)
    keys = [(r["step"], r["split"], r["name"]) for r in resumed]
    assert len(keys) == len(set(keys))  # no step logged twice
    expected = [r for r in rows(whole) if r["name"] != "train_seconds"]
    assert [r for r in resumed if r["name"] != "train_seconds"] == expected
    assert not list(run_dir.glob(".metrics*"))  # rewritten atomically: no temporary left behind


def test_step_seeds_give_independent_streams():
    seeds = [seed for step in range(4) for seed in train.step_seeds(0, step)]
    assert len(set(seeds)) == 8 and train.step_seeds(1, 0) != train.step_seeds(0, 0)
    global_seed, batch_seed = train.step_seeds(0, 0)
    first = torch.rand(16, generator=torch.Generator().manual_seed(global_seed))
    second = torch.rand(16, generator=torch.Generator().manual_seed(batch_seed))
    assert (first - second).abs().min() > 0  # no shared draws
    assert train.step_seeds(0, 3) == train.step_seeds(0, 3)


def test_checkpoints_load_without_running_pickled_code(tmp_path, reference):
    model, state = load_model(reference / "checkpoints" / "last.pt", task="head2neck")
    assert state["step"] == MAX_STEPS and state["config"]["task"]["name"] == "head2neck"
    torch.save({**state, "note": Path("a path object")}, tmp_path / "pickled.pt")  # not a plain container
    with pytest.raises(InputError, match=r"pickled\.pt: not a readable checkpoint"):
        load_checkpoint(tmp_path / "pickled.pt")


def test_a_checkpoint_of_another_layout_is_named(tmp_path, reference):
    state = load_checkpoint(reference / "checkpoints" / "last.pt")
    state["model"]["mlp.9.weight"] = torch.zeros(3, 3)
    save_checkpoint(tmp_path / "old.pt", state)
    with pytest.raises(InputError, match=r"old\.pt: checkpoint written by an incompatible version of the code: "
                                         r"its model state does not load .*mlp\.9\.weight"):
        load_model(tmp_path / "old.pt")
    state = load_checkpoint(reference / "checkpoints" / "last.pt")
    del state["model_config"]["residual_scale"]
    save_checkpoint(tmp_path / "older.pt", state)
    with pytest.raises(InputError, match=r"older\.pt: checkpoint written by an incompatible version of the code: "
                                         r"its model_config does not build .*missing \['residual_scale'\]"):
        load_model(tmp_path / "older.pt")
    # resuming from it: the same message, before any step is taken
    run_dir = tmp_path / "run"
    save_checkpoint(run_dir / "checkpoints" / "last.pt", load_checkpoint(tmp_path / "old.pt"))
    with pytest.raises(InputError, match=r"last\.pt: checkpoint written by an incompatible version of the code"):
        train.fit(config("resume=true"), run_dir)


def test_cli_refused_resume_is_an_error_with_status_2(tmp_path):
    """`python train.py resume=true` in a run folder without a checkpoint: the message, no traceback."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "train.py", "resume=true", f"hydra.run.dir={tmp_path / 'run'}",
                             "trainer.progress=false"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("error: ") and "last.pt" in result.stderr and "Traceback" not in result.stderr
