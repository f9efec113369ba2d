"""The training loop (tasks.loop, run by train.py) and checkpoints (models/checkpoint.py): resume checks,
metrics, seeds, loading.

Runs are tiny head2neck trainings (a few steps on a few synthetic sequences): the loop is task-agnostic.
"""
from __future__ import annotations

import csv
import re
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir

import tasks
from base.errors import InputError
from models.checkpoint import load_checkpoint, load_model, save_checkpoint
from tasks import loop

REPO = Path(__file__).resolve().parents[1]
MAX_STEPS = 6


# A tiny head2neck run (a few steps on a few synthetic sequences), also used by test_distributed.py.
TINY = ["task=head2neck", "model.hidden=[16]", "data.train_sequences=8", "data.val_sequences=2",
        "data.prior.seconds=1.0", "task.batch_size=64", f"trainer.max_steps={MAX_STEPS}", "trainer.eval_every=0",
        "trainer.log_every=1", "trainer.checkpoint_every=2", "trainer.progress=false", "trainer.threads=1",
        "optim.warmup_steps=2"]


def config(*overrides):
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("train", overrides=[*TINY, *overrides])


def rows(run_dir: Path) -> list[dict]:
    with open(run_dir / "metrics.csv", newline="") as f:
        return list(csv.DictReader(f))


def weights(run_dir: Path) -> dict:
    return load_checkpoint(run_dir / "checkpoints" / "last.pt")["model"]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """An uninterrupted run (logging every third step only: run control, not what is computed)."""
    run_dir = tmp_path_factory.mktemp("reference")
    loop.fit(config("trainer.log_every=3"), run_dir)
    return run_dir


def test_resume_refuses_another_config_and_accepts_other_run_control(tmp_path, reference):
    run_dir = tmp_path / "run"
    loop.fit(config("trainer.stop_after=3"), run_dir)
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"] == 3
    lr = config().optim.lr
    assert lr != 0.01
    with pytest.raises(InputError, match=r"last\.pt: resume=true with a config that differs from the checkpoint's "
                                         + re.escape(f"(optim.lr: {lr!r} -> 0.01); only resume, trainer.stop_after")):
        loop.fit(config("resume=true", "optim.lr=0.01"), run_dir)
    with pytest.raises(InputError, match=r"data\.seed: 1 -> 5; model\.hidden: \[16\] -> \[32\]"):
        loop.fit(config("resume=true", "data.seed=5", "model.hidden=[32]"), run_dir)
    with pytest.raises(InputError,
                       match="checkpoint of task 'head2neck', but resume=true runs task 'larynx_transformer'"):
        loop.fit(compose_larynx("resume=true"), run_dir)
    # stop_after and log_every differ from the first part: allowed, and the weights are the uninterrupted run's
    loop.fit(config("resume=true", "trainer.log_every=2"), run_dir)
    assert (run_dir / "eval.json").is_file()
    resumed, uninterrupted = weights(run_dir), weights(reference)
    assert resumed.keys() == uninterrupted.keys()
    assert all(torch.equal(resumed[k], uninterrupted[k]) for k in resumed)


def compose_larynx(*overrides):
    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        return compose("train", overrides=["task=larynx_transformer", "task.members=1", "trainer.progress=false",
                                           *overrides])


def test_resume_drops_the_metrics_logged_after_the_checkpoint(tmp_path, monkeypatch):
    from tasks.head2neck import Task

    whole = tmp_path / "whole"
    loop.fit(config(), whole)
    loss = Task.loss

    def interrupted(self, batch, step):
        if step == MAX_STEPS - 1:
            raise RuntimeError("interrupted")
        return loss(self, batch, step)

    run_dir = tmp_path / "run"
    monkeypatch.setattr(Task, "loss", interrupted)
    with pytest.raises(RuntimeError, match="interrupted"):
        loop.fit(config(), run_dir)
    monkeypatch.undo()
    checkpoint_step = load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"]
    assert checkpoint_step == MAX_STEPS - 2 and {int(r["step"]) for r in rows(run_dir)} == set(range(1, MAX_STEPS))
    loop.fit(config("resume=true"), run_dir)
    resumed = rows(run_dir)
    keys = [(r["step"], r["split"], r["name"]) for r in resumed]
    assert len(keys) == len(set(keys))  # no step logged twice
    expected = [r for r in rows(whole) if r["name"] != "train_seconds"]
    assert [r for r in resumed if r["name"] != "train_seconds"] == expected
    assert not list(run_dir.glob(".metrics*"))  # rewritten atomically: no temporary left behind


def test_step_seeds_give_independent_streams():
    seeds = [seed for step in range(4) for seed in loop.step_seeds(0, step)]
    assert len(set(seeds)) == 8 and loop.step_seeds(1, 0) != loop.step_seeds(0, 0)
    global_seed, batch_seed = loop.step_seeds(0, 0)
    first = torch.rand(16, generator=torch.Generator().manual_seed(global_seed))
    second = torch.rand(16, generator=torch.Generator().manual_seed(batch_seed))
    assert (first - second).abs().min() > 0  # no shared draws
    assert loop.step_seeds(0, 3) == loop.step_seeds(0, 3)


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
        loop.fit(config("resume=true"), run_dir)


def test_cli_refused_resume_is_an_error_with_status_2(tmp_path):
    """`python train.py resume=true` in a run folder without a checkpoint: the message, no traceback."""
    import subprocess
    import sys

    result = subprocess.run([sys.executable, "train.py", "resume=true", f"hydra.run.dir={tmp_path / 'run'}",
                             "trainer.progress=false"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2, result.stderr
    assert result.stderr.startswith("error: ") and "last.pt" in result.stderr and "Traceback" not in result.stderr



def test_cli_refused_data_leaves_no_run_folder(tmp_path):
    """Bad data refused before training: the message naming the path, status 2, and no run folder left behind
    (hydra's .hydra/ and log are removed with it)."""
    import subprocess
    import sys

    run_dir = tmp_path / "run"
    result = subprocess.run([sys.executable, "train.py", "task=larynx_transformer", "data=pairs",
                             f"data.path={tmp_path / 'missing'}", f"hydra.run.dir={run_dir}", "trainer.progress=false"],
                            cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2, result.stderr
    assert f"error: {tmp_path / 'missing'}: not a folder" in result.stderr and "Traceback" not in result.stderr
    assert not run_dir.exists(), list(run_dir.rglob("*"))
    # the default run folder (runs/<task>/<time>) of a first run: runs/ is not left behind either
    result = subprocess.run([sys.executable, str(REPO / "train.py"), "task=head2neck", "task.lambda_fk=-1",
                             "trainer.progress=false"], cwd=tmp_path, capture_output=True, text=True, timeout=300)
    assert result.returncode == 2 and "lambda_fk=-1.0: expected a non-negative weight" in result.stderr, result.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == [], list(tmp_path.rglob("*"))


# --------------------------------------------------------------------------- the loop's arithmetic


def test_single_process_run_is_the_documented_loop(tmp_path, monkeypatch):
    """loop.fit on one process (with the distributed, device and AMP code in place) gives bit-identical weights
    to the loop of tasks.loop's docstring written out here: seed, build, then per step the two step seeds, the
    batch, AdamW with the warm-up/cosine factor, clipping.  The loss draws from torch's global generator (as
    dropout would), so its seeding counts too."""
    from tasks.head2neck import Task

    original = Task.loss
    monkeypatch.setattr(Task, "loss", lambda self, batch, step: (lambda l, m: (l * (1 + torch.rand(())), m))(
        *original(self, batch, step)))
    cfg = config("trainer.grad_clip=0.002", "trainer.eval_every=3")
    loop.fit(cfg, tmp_path / "run")
    torch.manual_seed(cfg.seed)
    task = tasks.build(cfg)
    model = task.model
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.optim.lr, betas=tuple(cfg.optim.betas),
                                  weight_decay=cfg.optim.weight_decay)
    scheduler = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda s: loop.lr_factor(
        s, cfg.optim.warmup_steps, MAX_STEPS, cfg.optim.min_lr_factor))
    clipped = 0
    for step in range(MAX_STEPS):
        global_seed, batch_seed = loop.step_seeds(cfg.seed, step)
        torch.manual_seed(global_seed)
        batch = task.batch(step, torch.Generator().manual_seed(batch_seed))
        model.train()
        loss, _ = task.loss(batch, step)
        optimizer.zero_grad()
        loss.backward()
        clipped += float(torch.nn.utils.clip_grad_norm_(model.parameters(), 0.002)) > 0.002
        optimizer.step()
        scheduler.step()
    assert clipped == MAX_STEPS  # the clipping path is exercised
    trained = weights(tmp_path / "run")
    assert all(torch.equal(trained[k], v) for k, v in model.state_dict().items())


def optimiser_steps(monkeypatch) -> list[dict]:
    """Record, at every AdamW step, the learning rate it applies and the norm of the gradient it steps with."""
    records = []
    step = torch.optim.AdamW.step

    def recording(self, *args, **kwargs):
        grads = [p.grad for group in self.param_groups for p in group["params"] if p.grad is not None]
        records.append({"lr": self.param_groups[0]["lr"],
                        "grad_norm": float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads])))})
        return step(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.AdamW, "step", recording)
    return records


def test_warm_up_rises_linearly_to_the_learning_rate(tmp_path, monkeypatch):
    """Steps 0..W-1 apply lr (s+1)/W, step W the full lr (the cosine's start); the first update moves no
    weight by more than lr/W (Adam's first step is lr * g/|g| per weight), and the largest by that much."""
    warmup, lr = 4, 0.01
    cfg = config(f"optim.warmup_steps={warmup}", f"optim.lr={lr}", "optim.weight_decay=0.0")
    torch.manual_seed(cfg.seed)
    initial = {k: v.clone() for k, v in tasks.build(cfg).model.state_dict().items()}
    records = optimiser_steps(monkeypatch)
    loop.fit(cfg, tmp_path / "all")
    expected = [lr * (s + 1) / warmup for s in range(warmup)] + [lr]
    assert [r["lr"] for r in records[:warmup + 1]] == pytest.approx(expected, rel=1e-12)
    assert records[warmup + 1]["lr"] < lr  # then the cosine decays
    loop.fit(config(f"optim.warmup_steps={warmup}", f"optim.lr={lr}", "trainer.stop_after=1"), tmp_path / "one")
    moved = max(float((weights(tmp_path / "one")[k] - v).abs().max()) for k, v in initial.items())
    assert moved == pytest.approx(lr / warmup, rel=1e-3)


def test_gradient_clipping_bounds_the_gradient_of_a_huge_loss(tmp_path, monkeypatch):
    """A loss scaled by 1e6: with grad_clip=1 every step's gradient norm is 1 (the clip), without it millions."""
    from tasks.head2neck import Task

    original = Task.loss
    monkeypatch.setattr(Task, "loss", lambda self, batch, step: (lambda l, m: (l * 1e6, m))(
        *original(self, batch, step)))
    records = optimiser_steps(monkeypatch)
    loop.fit(config("trainer.grad_clip=1.0"), tmp_path / "clipped")
    clipped = [r["grad_norm"] for r in records]
    records.clear()
    loop.fit(config("trainer.grad_clip=0"), tmp_path / "free")
    free = [r["grad_norm"] for r in records]
    assert len(clipped) == len(free) == MAX_STEPS
    assert clipped == pytest.approx([1.0] * MAX_STEPS, rel=1e-5)
    assert min(free) > 1e3


# --------------------------------------------------------------------------- validation during training


def test_validation_during_training_scores_that_step_and_survives_an_interruption_there(tmp_path):
    """Validation rows at every eval_every step but the last (the final evaluation covers it) hold the task's
    evaluation of that step's weights; a run stopped at a validation step and resumed logs exactly the rows
    and trains exactly the weights of the uninterrupted run."""
    whole = tmp_path / "whole"
    loop.fit(config("trainer.eval_every=2"), whole)
    assert sorted({int(r["step"]) for r in rows(whole) if r["split"] == "val"}) == [2, 4]
    part = tmp_path / "part"
    loop.fit(config("trainer.eval_every=2", "trainer.stop_after=4"), part)
    model, _ = load_model(part / "checkpoints" / "last.pt")
    cfg = config("trainer.eval_every=2")
    torch.manual_seed(cfg.seed)
    task = tasks.build(cfg)
    task.model.load_state_dict(model.state_dict())
    task.model.eval()
    expected = task.evaluate()
    logged = {r["name"]: float(r["value"]) for r in rows(part) if r["split"] == "val" and r["step"] == "4"}
    assert logged.keys() == expected.keys()
    assert all(logged[k] == pytest.approx(expected[k], rel=1e-5, abs=1e-9) for k in expected)
    loop.fit(config("trainer.eval_every=2", "resume=true"), part)
    assert [r for r in rows(part) if r["name"] != "train_seconds"] == \
        [r for r in rows(whole) if r["name"] != "train_seconds"]
    assert all(torch.equal(weights(part)[k], v) for k, v in weights(whole).items())


def test_resuming_a_finished_run_replaces_its_final_rows(tmp_path):
    run_dir = tmp_path / "run"
    loop.fit(config(), run_dir)
    before = [r for r in rows(run_dir) if r["name"] != "train_seconds"]
    assert sum(r["split"] == "final" for r in before) > 0
    loop.fit(config("resume=true"), run_dir)
    assert [r for r in rows(run_dir) if r["name"] != "train_seconds"] == before


def test_a_new_run_in_the_folder_of_another_is_refused(tmp_path):
    loop.fit(config("trainer.stop_after=2"), tmp_path / "run")
    with pytest.raises(InputError, match=r"last\.pt: this run directory already holds a run; resume=true continues"):
        loop.fit(config(), tmp_path / "run")


# --------------------------------------------------------------------------- early stopping, best weights


def distance_to(target: dict):
    """A task evaluate() whose val_loss is the squared distance of the model's weights to ``target``."""
    def evaluate(self, final: bool = False) -> dict[str, float]:
        state = self.model.state_dict()
        return {"val_loss": sum(float(((state[k].double() - v.double()) ** 2).sum()) for k, v in target.items())}
    return evaluate


def test_early_stopping_keeps_the_best_weights_and_evaluates_them(tmp_path, monkeypatch):
    """val_loss = distance to the weights after step 2: lowest (0) at step 2, so with patience 2 and a
    validation per step the run stops after step 4, best.pt holds step 2's weights, and the final evaluation
    (restore_best) scores them; an interruption between the best and the stop changes none of it, and a
    resumed early-stopped run trains no further."""
    from tasks.head2neck import Task

    loop.fit(config("trainer.stop_after=2"), tmp_path / "two")
    at_two = weights(tmp_path / "two")
    monkeypatch.setattr(Task, "evaluate", distance_to(at_two))
    settings = ("trainer.eval_every=1", "trainer.early_stopping_patience=2", "trainer.restore_best=true",
                "trainer.checkpoint_every=3")  # the stop (step 4) is saved although no checkpoint is due
    run_dir = tmp_path / "run"
    final = loop.fit(config(*settings), run_dir)
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"] == 4
    assert max(int(r["step"]) for r in rows(run_dir) if r["split"] != "final") == 4
    best = load_checkpoint(run_dir / "checkpoints" / "best.pt")
    assert best["step"] == 2 and best["val_loss"] == 0.0
    assert all(torch.equal(best["model"][k], v) for k, v in at_two.items())
    assert not all(torch.equal(weights(run_dir)[k], v) for k, v in at_two.items())  # last.pt: the last weights
    assert final["val_loss"] == 0.0 and final["best_step"] == 2.0 and final["best_val_loss"] == 0.0
    load_model(run_dir / "checkpoints" / "best.pt", task="head2neck")  # loads like last.pt

    interrupted = tmp_path / "interrupted"
    loop.fit(config(*settings, "trainer.stop_after=3"), interrupted)
    resumed = loop.fit(config(*settings, "resume=true"), interrupted)
    assert {k: v for k, v in resumed.items() if k != "train_seconds"} == \
        {k: v for k, v in final.items() if k != "train_seconds"}
    assert all(torch.equal(weights(interrupted)[k], v) for k, v in weights(run_dir).items())
    again = loop.fit(config(*settings, "resume=true"), run_dir)
    assert load_checkpoint(run_dir / "checkpoints" / "last.pt")["step"] == 4 and again["val_loss"] == 0.0
    with pytest.raises(InputError, match=r"only resume, trainer\.stop_after.*trainer\.log_every, "
                                         r"trainer\.checkpoint_every"):
        loop.fit(config(*settings, "resume=true", "trainer.eval_every=2"), run_dir)  # it chose the weights


def test_without_restore_best_the_final_evaluation_scores_the_last_weights(tmp_path, monkeypatch):
    from tasks.head2neck import Task

    loop.fit(config("trainer.stop_after=2"), tmp_path / "two")
    monkeypatch.setattr(Task, "evaluate", distance_to(weights(tmp_path / "two")))
    final = loop.fit(config("trainer.eval_every=1"), tmp_path / "run")
    assert final["val_loss"] > 0 and final["best_step"] == 2.0  # trained to the end: no patience
    assert load_checkpoint(tmp_path / "run" / "checkpoints" / "best.pt")["step"] == 2
    # the last step is scored by the final evaluation alone
    assert {int(r["step"]) for r in rows(tmp_path / "run") if r["split"] == "val"} == set(range(1, MAX_STEPS))


def test_the_final_evaluation_counts_for_the_best_weights(tmp_path, monkeypatch):
    """val_loss = distance to the last weights: the validations never reach 0, the final evaluation does, so
    best.pt holds the last weights (written at the end)."""
    from tasks.head2neck import Task

    loop.fit(config(), tmp_path / "whole")
    monkeypatch.setattr(Task, "evaluate", distance_to(weights(tmp_path / "whole")))
    final = loop.fit(config("trainer.eval_every=2"), tmp_path / "run")
    best = load_checkpoint(tmp_path / "run" / "checkpoints" / "best.pt")
    assert best["step"] == MAX_STEPS and best["val_loss"] == 0.0 and final["best_step"] == MAX_STEPS
    assert min(float(r["value"]) for r in rows(tmp_path / "run") if r["name"] == "val_loss" and r["split"] == "val") > 0
    # restore_best validates the last step too: the last weights are the best, and stay
    final = loop.fit(config("trainer.eval_every=2", "trainer.restore_best=true"), tmp_path / "restoring")
    assert final["best_step"] == MAX_STEPS and final["val_loss"] == 0.0


def test_early_stopping_needs_a_val_loss_and_validation(tmp_path):
    with pytest.raises(InputError, match=r"need a val_loss from the task's evaluation, which returned joint_err_deg"):
        loop.fit(config("trainer.eval_every=2", "trainer.early_stopping_patience=2"), tmp_path / "a")
    with pytest.raises(InputError, match=r"trainer: early_stopping_patience and restore_best need validation during "
                                         r"training: eval_every is 0"):
        loop.fit(config("trainer.restore_best=true"), tmp_path / "b")
    with pytest.raises(InputError, match=r"trainer: early_stopping_patience is 0, expected at least 1"):
        loop.fit(config("trainer.eval_every=1", "trainer.early_stopping_patience=0"), tmp_path / "c")
