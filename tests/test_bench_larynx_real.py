"""The real-regime benchmark's account of where the error lies (benchmarks/bench_larynx_real.py):
its swallow frames are where the swallow moves tau, and nowhere else."""
import argparse
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_larynx_real as bench  # noqa: E402
import larynx_families as families  # noqa: E402
import score_members  # noqa: E402

from data.pairs import LarynxSequence  # noqa: E402


def closing_jaw(open_frames: int = 60, frames: int = 300) -> np.ndarray:
    """psi [frames,55]: the jaw open (0.5) for ``open_frames`` frames, then closed; all else at rest."""
    psi = np.zeros((frames, 55), np.float32)
    psi[:open_frames, families.K["jawOpen"]] = 0.5
    return psi


def test_swallow_frames_follow_the_cue_and_the_duration():
    """Subject family: a swallow starts once the jaw has been closed 0.3 s (9 frames at 30 fps) and lasts
    0.7 + 2 tau_a seconds; the frames marked are inside that span and fill most of it."""
    psi = closing_jaw()
    for subject in range(3):
        p = families.person("subject", subject, seed=0, terms=5)
        mask = families.swallow_frames("subject", psi, subject, seed=0)
        onset = 60 + 9 - 1  # the first frame where the closure has held 9 frames
        end = onset + int(np.ceil((0.7 + 2 * p.tau_a) * families.FPS))
        assert not mask[:onset].any() and not mask[end + 1:].any(), (subject, np.flatnonzero(mask)[[0, -1]])
        assert mask[onset:end + 1].mean() > 0.8, (subject, mask[onset:end + 1].mean())


def test_no_swallow_while_the_jaw_stays_open():
    psi = closing_jaw(open_frames=300)
    assert not families.swallow_frames("damped", psi, 0, seed=1).any()


def test_split_rmse_puts_each_error_on_its_side():
    tau = np.zeros(10, np.float32)
    sequence = LarynxSequence(np.zeros((10, 55), np.float32), tau, 30.0, "s0", "a")
    mask = np.arange(10) < 4
    prediction = np.where(mask, 0.02, 0.005)
    inside, outside = bench.split_rmse([prediction], [sequence], [mask])
    assert abs(inside - 0.02) < 1e-9 and abs(outside - 0.005) < 1e-9
    inside, outside = bench.split_rmse([prediction], [sequence], [np.zeros(10, bool)])  # a take without swallows
    assert np.isnan(inside) and abs(outside - np.sqrt(np.mean(prediction ** 2))) < 1e-9


def test_fire_waits_out_the_refractory_time_from_a_swallow_before_the_take():
    cue = np.zeros(300, bool)
    for start in (10, 100, 200):
        cue[start:start + 5] = True
    assert families.fire(cue, 3.0) == [10, 100, 200]               # no swallow before the take
    assert families.fire(cue, 3.0, since=1.0) == [100, 200]        # 1 s before frame 0: frame 10 is 1.3 s later
    assert families.fire(cue, 3.0, since=3.0) == [10, 100, 200]


def talking_jaw(minutes: float) -> np.ndarray:
    """psi: the jaw open 1 s, then shut 4 s, over and over: a pause cue for every family every 5 s."""
    frames = int(minutes * 60 * families.FPS)
    psi = np.zeros((frames, 55), np.float32)
    psi[(np.arange(frames) % int(5 * families.FPS)) < families.FPS, families.K["jawOpen"]] = 0.5
    return psi


def test_physiological_spacing_swallows_about_once_a_minute():
    """The families' own refractory times swallow at nearly every cue (12 a minute here); with
    PHYSIOLOGICAL_SPACING each person swallows inside the spontaneous rate's confidence interval on average
    (0.67-1.42 a minute, the review cited beside it), on a take of 10 minutes, and the articulation is unchanged."""
    psi = talking_jaw(10.0)
    for family in ("damped", "saturating", "subject"):
        own = [len(families.swallow_onsets(families.swallow_frames(family, psi, s, 0))) / 10 for s in range(3)]
        assert min(own) >= 6, (family, own)
        spaced_masks = [families.swallow_frames(family, psi, s, seed, 7, families.PHYSIOLOGICAL_SPACING)
                        for s in range(3) for seed in range(4)]
        rates = [len(families.swallow_onsets(mask)) / 10 for mask in spaced_masks]
        assert 0.67 <= np.mean(rates) <= 1.42 and max(rates) <= 1.8, (family, rates)
        spaced = families.family_tau(family, psi, 1, 0, 7, families.PHYSIOLOGICAL_SPACING)
        own_tau = families.family_tau(family, psi, 1, 0, 7)
        swallowing = families.swallow_frames(family, psi, 1, 0) | families.swallow_frames(family, psi, 1, 0, 7,
                                                                                   families.PHYSIOLOGICAL_SPACING)
        np.testing.assert_allclose(spaced[~swallowing], own_tau[~swallowing], atol=1e-4)  # the masks end at 1e-4


def test_spacing_draws_a_refractory_time_per_person_and_a_phase_per_take():
    people = [families.person("damped", s, 0, 5, families.PHYSIOLOGICAL_SPACING, take=t)
              for s in range(3) for t in (1, 2)]
    low, high = families.PHYSIOLOGICAL_SPACING
    assert all(low <= p.refractory <= high and 0 <= p.since <= p.refractory for p in people)
    assert people[0].refractory == people[1].refractory and people[0].since != people[1].since
    assert len({p.refractory for p in people}) == 3
    plain = families.person("damped", 0, 0, 5)
    assert plain.refractory is None and plain.since is None and plain.gain == people[0].gain


@pytest.mark.parametrize("bad", ["40,20", "fast", "0,5"])
def test_swallow_spacing_option_names_what_it_expects(bad, capsys):
    parser = argparse.ArgumentParser()
    assert bench.swallow_spacing(parser, "family") is None
    assert bench.swallow_spacing(parser, "physiological") == families.PHYSIOLOGICAL_SPACING
    assert bench.swallow_spacing(parser, "20,40") == (20.0, 40.0)
    with pytest.raises(SystemExit):
        bench.swallow_spacing(parser, bad)
    assert f"--swallow-spacing: {bad}; expected family, physiological or LOW,HIGH seconds" in capsys.readouterr().err


def test_the_ensemble_summary_compares_the_spread_with_the_single_networks():
    """Four training seeds: the ensembles' ratios 0.70 0.72 0.71 0.73 (std 0.0112, range 0.03) against their
    member 0's 0.60 0.90 0.70 0.80 (std 0.112, range 0.30): both spread ratios 0.10; the first two members too."""
    runs = [{"transformer": e, "ridge": 1.0, "member0": m0, "member1": m1, "first2": f2, "transformer_average_style": e,
             "gru": np.nan, "mean": 1.0, "swallow_fraction": 0.1, "swallows_per_minute": 2.0,
             **{f"{m}_{part}": 0.5 for m in ("transformer", "ridge", "gru", "mean")
                for part in ("in_swallows", "outside")}}
            for e, m0, m1, f2 in ((0.70, 0.60, 0.8, 0.70), (0.72, 0.90, 0.6, 0.75), (0.71, 0.70, 0.7, 0.70),
                                  (0.73, 0.80, 0.6, 0.70))]
    text = bench.summarise({"effort": runs})
    line = next(row for row in text.splitlines() if row.startswith("effort") and "ensemble" in row)
    assert "= 0.715 +- 0.011 (range 0.030)" in line and "= 0.750 +- 0.112 (range 0.300)" in line
    assert "spread ratio 0.10 (std), 0.10 (range)" in line
    first = next(row for row in text.splitlines() if "the first 2 members" in row)
    assert "0.700 0.750 0.700 0.700 = 0.712" in first and "spread ratio 0.19 (std)" in first


def test_the_summary_gives_the_same_runs_without_refit():
    """Refit members: the ensemble of the members' weights before their refits (fold_ensemble) and member 0's
    before it (the network task.members=1 trains) are summarised from the same runs, with the refit ensemble's
    spread against that member 0's: 0.0112 / 0.0500 = 0.22."""
    runs = [{"transformer": e, "ridge": 1.0, "member0": 0.7, "fold_ensemble": f, "fold_member0": f0,
             "transformer_average_style": e, "gru": np.nan, "mean": 1.0, "swallow_fraction": 0.1,
             "swallows_per_minute": 2.0, **{f"{m}_{part}": 0.5 for m in ("transformer", "ridge", "gru", "mean")
                                            for part in ("in_swallows", "outside")}}
            for e, f, f0 in ((0.70, 0.80, 0.50), (0.72, 0.82, 0.60), (0.71, 0.84, 0.50), (0.73, 0.86, 0.60))]
    text = bench.summarise({"damped": runs})
    line = next(row for row in text.splitlines() if "without refit" in row)
    assert "ensemble 0.800 0.820 0.840 0.860 = 0.830 +- 0.022" in line
    assert "member 0 (task.members=1) 0.500 0.600 0.500 0.600 = 0.550 +- 0.050" in line
    assert "spread / member 0's 0.22" in line


def test_fold_weights_give_each_members_heldout_tau_and_their_trimmed_mean(tmp_path):
    """A run whose three members refit: fold_member_taus reads each member's weights before its refit
    (members/<k>/checkpoints/best.pt), returns their held-out tau [members, sequences, frames] for scoring other
    combinations later; ensemble_rmse gives the RMSE of the per-frame middle of the three (their trimmed mean)."""
    from test_larynx_ensemble import member

    from models.checkpoint import save_checkpoint
    from models.larynx import predict_tau

    run = tmp_path / "run"
    nets = [member(seed) for seed in range(3)]
    for k, net in enumerate(nets):
        (run / "members" / str(k) / "refit").mkdir(parents=True)
        save_checkpoint(run / "members" / str(k) / "checkpoints" / "best.pt",
                        {"task": "larynx_transformer", "model_config": net.config, "model": net.state_dict()})
    rng = np.random.default_rng(0)
    heldout = [LarynxSequence(rng.uniform(0, 0.5, (90, 55)).astype(np.float32),
                              rng.normal(0.01, 0.02, 90).astype(np.float32), 30.0, subject, f"take_{subject}")
               for subject in ("anna", "ben")]
    fold = np.asarray(bench.fold_member_taus(run, heldout))
    assert fold.shape == (3, 2, 90)
    expected = np.stack([[predict_tau(net, s.psi, s.subject) for s in heldout] for net in nets])
    assert np.allclose(fold, expected, atol=1e-6)
    middle = np.median(expected, axis=0)
    rmse = np.sqrt(np.mean((middle - np.stack([s.tau for s in heldout])) ** 2))
    assert score_members.ensemble_rmse(np.asarray(fold), np.stack([s.tau for s in heldout])) == pytest.approx(
        rmse, rel=1e-5)
    assert bench.fold_member_taus(tmp_path / "none", heldout) == []
