"""Ensembles of larynx transformers (models.larynx.ensemble, tasks.members): members averaged, streamed in one
batched step, trained on their own seeds and validation folds, written as one checkpoint."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
from test_larynx_transformer import shifted_channel_pairs, tiny_config

from base.errors import InputError
from data.pairs import LarynxSequence, split_by_take
from models.checkpoint import load_model, save_checkpoint
from models.larynx import (
    LarynxDataFields,
    LarynxEnsemble,
    LarynxTransformer,
    LarynxTransformerConfig,
    build_model,
    ensemble_of,
    predict_tau,
    trimmed_mean,
)
from tasks.members import member_config, member_seed, refit_config, train
from tests.larynx_reference import state_bytes

SIZES = LarynxTransformerConfig(d_model=16, n_heads=2, d_ff=24, window=8, expression_dilations=[1, 2],
                                smoothing_frames=16.0, dropout=0.0)


def member(seed: int, subjects=("anna", "ben"), tau_mean=0.01, tau_scale=0.02) -> LarynxTransformer:
    """A network with random weights everywhere (the style tables and head too, so members differ in each)."""
    torch.manual_seed(seed)
    model = LarynxTransformer(SIZES, LarynxDataFields(30.0, list(subjects), tau_mean, tau_scale))
    with torch.no_grad():
        for table in (model.style.weight, model.style_gain.weight, model.head.weight):
            table.normal_(0.0, 0.3)
    return model.eval()


def test_the_stream_is_the_trimmed_mean_of_the_members(tmp_path):
    """Four members of other weights and tau normalisations: the ensemble's streamed tau (generate, frame by
    frame step, and the whole-sequence forward) is, frame by frame, the mean of the two members' forward left
    when the lowest and the highest are dropped."""
    members = [member(s, tau_mean=0.01 * s, tau_scale=0.02 + 0.01 * s) for s in range(4)]
    ensemble = LarynxEnsemble(members).eval()
    psi = torch.rand(2, 150, 55)
    subject = torch.tensor([1, 2])
    taus = torch.stack([m(psi, subject) for m in members])  # [4,B,T]
    low, high = taus.min(0).values, taus.max(0).values
    expected = (taus.sum(0) - low - high) / 2
    assert torch.allclose(ensemble(psi, subject), expected, atol=1e-6)
    assert torch.allclose(ensemble.generate(psi, subject, chunk=40), expected, atol=1e-5)
    stream = ensemble.stream(2, subject)
    stepped = torch.stack([stream.step(psi[:, t]) for t in range(psi.shape[1])], dim=1)
    assert torch.allclose(stepped, expected, atol=1e-5)
    # Members differ: the mean is not any one of them
    assert min((m(psi, subject) - expected).abs().max().item() for m in members) > 1e-3


def test_a_member_far_off_the_others_moves_the_ensemble_little():
    """Per frame the lowest and the highest member are dropped (K >= 3): a member 100x off leaves the mean of the
    middle three; two members are averaged, one is itself."""
    tau = torch.tensor([[1.0, 0.0], [2.0, 0.1], [3.0, 0.2], [100.0, -50.0], [2.5, 0.3]])  # [K=5, frames=2]
    assert torch.allclose(trimmed_mean(tau), torch.tensor([2.5, 0.1]))
    assert torch.allclose(trimmed_mean(tau[:2]), torch.tensor([1.5, 0.05]))
    assert torch.equal(trimmed_mean(tau[3:4]), tau[3])


def test_streams_share_one_weight_snapshot_until_a_weight_changes():
    """Streams of the same weights read one snapshot (a phone each in the live receiver); an in-place change of
    a parameter (an optimiser step) or of a buffer gives the next stream a new snapshot, and the streams made
    before decode as they did."""
    ensemble = LarynxEnsemble([member(s) for s in range(2)]).eval()
    psi = torch.rand(1, 20, 55)
    first, second = ensemble.stream(), ensemble.stream()
    assert first.weights is second.weights
    before = torch.stack([first.step(psi[:, t]) for t in range(20)])
    with torch.no_grad():
        ensemble.members[1].head.weight.mul_(2.0)
    changed = ensemble.stream()
    assert changed.weights is not first.weights
    after = torch.stack([changed.step(psi[:, t]) for t in range(20)])
    assert (after - before).abs().max().item() > 1e-4
    assert torch.allclose(torch.stack([second.step(psi[:, t]) for t in range(20)]), before, atol=1e-7)
    ensemble.members[0].tau_mean.add_(0.5)
    shifted = ensemble.stream()
    assert shifted.weights is not changed.weights
    assert torch.allclose(torch.stack([shifted.step(psi[:, t]) for t in range(20)]), after + 0.25, atol=1e-5)
    ensemble.double()  # cast in place of the same parameters: a new snapshot in float64
    cast = ensemble.stream()
    assert cast.weights is not shifted.weights and cast.weights.head[1].dtype == torch.float64


def test_a_one_member_ensemble_is_its_network():
    network = member(4)
    psi = torch.rand(1, 90, 55)
    assert torch.equal(LarynxEnsemble([network]).generate(psi), network.generate(psi))
    assert state_bytes(network.stream()) * 3 == state_bytes(LarynxEnsemble([member(s) for s in range(3)]).stream())


def test_subject_tables_are_joined_and_unknown_subjects_get_the_average_person():
    """Members trained on other people: the ensemble knows the union; a member that never saw a person gives
    them its average person (row 0)."""
    a, b = member(0, ["anna", "ben"]), member(1, ["ben", "cleo"])
    ensemble = ensemble_of([a, b])
    assert ensemble.subjects == ["anna", "ben", "cleo"]
    psi = np.random.default_rng(0).random((80, 55)).astype(np.float32)
    for name, in_a, in_b in (("anna", "anna", None), ("ben", "ben", "ben"), ("cleo", None, "cleo")):
        expected = 0.5 * (predict_tau(a, psi, in_a) + predict_tau(b, psi, in_b))
        assert np.allclose(predict_tau(ensemble, psi, name), expected, atol=1e-6), name
    with pytest.raises(InputError, match="subject 'dora' was not in the training data"):
        predict_tau(ensemble, psi, "dora")


def test_members_of_other_sizes_are_refused_and_a_bad_ensemble_config_named(tmp_path):
    other = LarynxTransformer(LarynxTransformerConfig(d_model=32, n_heads=2, window=8),
                              LarynxDataFields(30.0, ["anna", "ben"], 0.0, 1.0))
    with pytest.raises(ValueError, match="ensemble member 1 has other sizes than member 0"):
        LarynxEnsemble([member(0), other])
    with pytest.raises(ValueError, match="expected 'members' alone, a non-empty list"):
        build_model({"members": []})
    save_checkpoint(tmp_path / "bad.pt", {"task": "larynx_transformer", "model_config": {"members": [], "fps": 30},
                                          "model": {}})
    with pytest.raises(InputError, match="bad.pt: checkpoint written by an incompatible version.*'members' alone"):
        load_model(tmp_path / "bad.pt", "larynx_transformer")


def test_validation_folds_partition_the_takes_and_fold_zero_is_the_single_split():
    pairs = [LarynxSequence(np.zeros((10, 55), np.float32), np.zeros(10, np.float32), 30.0, "anna", f"take{t}")
             for t in range(10) for _ in range(2)]
    single = split_by_take(pairs, 0.2, 0)[1]
    folds = [split_by_take(pairs, 0.2, 0, fold=k, folds=5) for k in range(5)]
    assert [p.take for p in folds[0][1]] == [p.take for p in single]
    held = [sorted({p.take for p in val}) for _, val in folds]
    assert all(len(h) == 2 for h in held)
    assert sorted(t for h in held for t in h) == sorted({p.take for p in pairs})  # each take validated once
    for training, val in folds:
        assert not {p.take for p in training} & {p.take for p in val}
    with pytest.raises(InputError, match="validation fold 5 of 5"):
        split_by_take(pairs, 0.2, 0, fold=5, folds=5)


def test_member_seeds_are_independent_across_training_seeds():
    """Member 0 is the run of the seed itself; no two members of training seeds 0-9 share a seed."""
    assert member_seed(7, 0) == 7
    seeds = [member_seed(s, k) for s in range(10) for k in range(5)]
    assert len(set(seeds)) == len(seeds)


@pytest.mark.slow
def test_an_ensemble_trains_as_members_on_their_folds_and_loads_as_one_model(tmp_path, capsys):
    """train.py task.members=3 on pairs: three runs in members/<k>/ (member 0 the run of the seed itself, each
    validated on another take), each refit on every take for its best step in members/<k>/refit/, then
    checkpoints/best.pt holds the ensemble of the refits, which predicts their trimmed mean and which
    task.init_from takes member by member.  On takes from a generator shifted in what the larynx ignores, the
    ensemble beats ridge and is at least as good as its members on average."""
    from tasks import loop
    from tasks.larynx_transformer import Task, fit_ridge, rmse, window_features

    shifted_channel_pairs(tmp_path / "pairs", 6, 400, seed=1, other_level=0.2)
    heldout = shifted_channel_pairs(None, 2, 400, seed=2, other_level=0.7)
    overrides = ["data=pairs", f"data.path={tmp_path / 'pairs'}", "data.val_fraction=0.2", "task.crop=64",
                 "model.window=16", "trainer.max_steps=150", "trainer.eval_every=30", "trainer.restore_best=true",
                 "model.dropout=0", "task.members=3"]
    cfg = tiny_config(overrides, data=[])
    result = train(cfg, tmp_path / "run")
    out = capsys.readouterr().out
    assert "member 3 of 3" in out and "3 members, each scored on its own validation, mean rmse" in out
    validated = [{s.take for s in Task(tiny_config([*overrides, f"task.member={k}"], data=[])).val} for k in range(3)]
    assert len(validated[0] | validated[1] | validated[2]) == 3  # each member validates on another take
    ensemble = load_model(tmp_path / "run" / "checkpoints" / "best.pt", "larynx_transformer")[0]
    assert isinstance(ensemble, LarynxEnsemble) and len(ensemble.members) == 3
    takes = {s.take for s in Task(tiny_config(overrides, data=[])).train} | validated[0]
    for k in range(3):  # a refit trains on every take, for as many steps as its fold chose
        steps = result[f"member{k}_best_step"]
        assert result[f"member{k}_refit_steps"] == steps and 30 <= steps <= 150 and steps % 30 == 0
        refit = Task(tiny_config([*overrides, f"task.member={k}", f"task.refit_steps={int(steps)}"], data=[]))
        assert {s.take for s in refit.train} == takes and len(takes) == 6
        state = torch.load(tmp_path / "run" / "members" / str(k) / "refit" / "checkpoints" / "last.pt",
                           weights_only=True)
        assert state["step"] == steps and state["config"]["trainer"]["eval_every"] == 0
    single = [load_model(tmp_path / "run" / "members" / str(k) / "refit" / "checkpoints" / "last.pt")[0]
              for k in range(3)]
    predictions = [predict_tau(ensemble, s.psi, "anna") for s in heldout]
    alone = [[predict_tau(m, s.psi, "anna") for s in heldout] for m in single]
    # three members: the trimmed mean is each frame's middle member
    assert all(np.allclose(p, np.median([a[i] for a in alone], axis=0), atol=1e-6) for i, p in enumerate(predictions))
    assert result["rmse"] == pytest.approx(np.mean([result[f"member{k}_rmse"] for k in range(3)]))
    # the member of seed 0 and fold 0 is the run task.members=1 gives
    one = loop.fit(tiny_config([*overrides[:-1], "task.members=1"], data=[]), tmp_path / "one")
    assert one["rmse"] == pytest.approx(result["member0_rmse"], rel=1e-6)

    training = shifted_channel_pairs(None, 6, 400, seed=1, other_level=0.2)
    weights, _ = fit_ridge(training, 30, [1.0, 100.0, 1e4])
    ridge = rmse([window_features(s.psi, 30) @ weights for s in heldout], heldout)
    ensemble_rmse = rmse(predictions, heldout)
    assert ensemble_rmse <= np.mean([rmse(a, heldout) for a in alone]) + 1e-9
    assert ensemble_rmse < ridge, (ensemble_rmse, ridge)

    # task.init_from of an ensemble: member k starts from its member k
    warm = Task(tiny_config([*overrides, f"task.init_from={tmp_path / 'run' / 'checkpoints' / 'best.pt'}",
                             "task.member=2"], data=[]))
    assert torch.equal(warm.model.head.weight, ensemble.members[2].head.weight)


def test_an_ensemble_of_synthetic_runs_is_scored_on_their_shared_validation(tmp_path):
    """data=synthetic: every member validates on the same new takes and people, so eval.json also holds the
    ensemble's own score there (ensemble_rmse), which is the RMSE of its streamed predictions; no member refits
    (its validation is no training data), and a refit asked for is refused by name."""
    from tasks import loop
    from tasks.larynx_transformer import Task, rmse

    data = ["data.train_subjects=2", "data.sequences_per_subject=1", "data.seconds=8", "data.heldout_subjects=1",
            "data.heldout_sequences_per_subject=1"]
    cfg = tiny_config(["trainer.max_steps=4", "task.members=2"], data)
    result = train(cfg, tmp_path / "run")
    ensemble = load_model(tmp_path / "run" / "checkpoints" / "best.pt", "larynx_transformer")[0]
    task = Task(tiny_config(["trainer.max_steps=4", "task.members=2", "task.member=0"], data))
    predictions = [predict_tau(ensemble, s.psi, s.subject if s.subject in ensemble.subjects else None)
                   for s in task.val]
    assert result["ensemble_rmse"] == pytest.approx(rmse(predictions, task.val), rel=1e-5)
    assert "ensemble_rmse" not in loop.fit(tiny_config(["trainer.max_steps=4", "task.members=1"], data),
                                           tmp_path / "one")
    assert not (tmp_path / "run" / "members" / "0" / "refit").exists() and "member0_refit_steps" not in result
    with pytest.raises(InputError, match=r"task.refit_steps=4: a refit trains on the validation takes of "
                                         r"data=pairs; data=synthetic validates on data of its own"):
        Task(tiny_config(["task.refit_steps=4"], data))


@pytest.mark.slow
def test_resuming_an_ensemble_continues_its_members_and_starts_the_ones_never_started(tmp_path):
    """An ensemble stopped after its first member (its refit half done, the second member never started):
    resume=true finishes the refit, trains the second member, and gives the uninterrupted run's weights."""
    import shutil

    from tasks import loop

    shifted_channel_pairs(tmp_path / "pairs", 4, 200, seed=1, other_level=0.2)
    overrides = ["data=pairs", f"data.path={tmp_path / 'pairs'}", "data.val_fraction=0.5", "task.crop=48",
                 "model.window=16", "trainer.max_steps=20", "trainer.eval_every=10", "trainer.restore_best=true",
                 "trainer.checkpoint_every=5", "model.dropout=0", "task.members=2"]
    train(tiny_config(overrides, data=[]), tmp_path / "whole")
    train(tiny_config(overrides, data=[]), tmp_path / "run")
    refit = tmp_path / "run" / "members" / "0" / "refit"
    steps = torch.load(refit / "checkpoints" / "last.pt", weights_only=True)["step"]
    shutil.rmtree(tmp_path / "run" / "members" / "1")
    shutil.rmtree(tmp_path / "run" / "checkpoints")
    shutil.rmtree(refit)
    half = refit_config(member_config(tiny_config(overrides, data=[]), 0), steps)
    half.trainer.stop_after = 5
    assert loop.fit(half, refit) == {}  # the refit stopped at step 5
    assert torch.load(refit / "checkpoints" / "last.pt", weights_only=True)["step"] == 5 < steps
    train(tiny_config([*overrides, "resume=true"], data=[]), tmp_path / "run")
    whole, resumed = (torch.load(tmp_path / r / "checkpoints" / "best.pt", weights_only=True)["model"]
                      for r in ("whole", "run"))
    assert whole.keys() == resumed.keys() and all(torch.equal(whole[k], resumed[k]) for k in whole)


def small_ensemble(folder: Path) -> list[str]:
    """train.py overrides (beside TINY_LARYNX) of three small members on four takes written to ``folder``,
    refitting after 8 steps at most."""
    shifted_channel_pairs(folder, 4, 100, seed=1, other_level=0.2)
    return ["data=pairs", f"data.path={folder}", "data.val_fraction=0.3", "task.crop=24", "model.window=8",
            "model.d_model=16", "model.n_heads=2", "model.d_ff=24", "model.expression_dilations=[1,2]",
            "model.smoothing_frames=16", "task.batch_size=4", "task.ridge_window=0.1", "trainer.max_steps=8",
            "trainer.eval_every=4", "trainer.restore_best=true", "task.members=3"]


def test_members_trained_in_parallel_processes_equal_the_sequential_run(tmp_path):
    """trainer.member_workers=2 (two spawned processes share the three members and their refits) and one job per
    member (task.member=k, then resume=true): every member's weights, the refits', the ensemble's and eval.json's
    figures equal the one-process run's bit for bit."""
    overrides = small_ensemble(tmp_path / "pairs")
    sequential = train(tiny_config(overrides, data=[]), tmp_path / "one")
    parallel = train(tiny_config([*overrides, "trainer.member_workers=2"], data=[]), tmp_path / "two")
    # one job per member (a sweep over task.member, e.g. on SLURM), then a resumed run writes the ensemble
    for k in range(3):
        train(tiny_config([*overrides, f"task.member={k}"], data=[]), tmp_path / "jobs" / "members" / str(k))
    jobs = train(tiny_config([*overrides, "resume=true"], data=[]), tmp_path / "jobs")
    timing = [key for key in sequential if key.endswith("train_seconds")]
    for result in (parallel, jobs):
        assert {k: v for k, v in result.items() if k not in timing} == {
            k: v for k, v in sequential.items() if k not in timing}
    files = sorted(p.relative_to(tmp_path / "one") for p in (tmp_path / "one").rglob("*.pt"))
    assert len(files) == 2 + 3 * 4  # the ensemble's best and last, each member's and each refit's
    for name in files:
        one, two, three = (torch.load(tmp_path / run / name, weights_only=True)["model"]
                           for run in ("one", "two", "jobs"))
        for other in (two, three):
            assert one.keys() == other.keys() and all(torch.equal(one[k], other[k]) for k in one), name
