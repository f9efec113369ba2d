"""benchmarks/bench_larynx_cues.py: the per-cue scores are what they say, on predictors whose errors are known."""
from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_larynx_cues as bench  # noqa: E402

from data.synthetic_larynx import SWALLOW_CUES, TRAINING_RANGES, larynx_response, subject_params  # noqa: E402

CUES = ("pause", "blink")
RANGES = dataclasses.replace(TRAINING_RANGES, cues=CUES)


def person_of(sequence):
    return subject_params(int(sequence.subject[1:]), bench.SEED, RANGES)


def test_an_oracle_scores_the_tracker_noise_and_a_swallow_blind_one_the_swallows():
    """Predicting the noise-free tau leaves the generator's tau noise (std 0.0005) everywhere; predicting it
    without swallows leaves their RMS (plus that noise), inside them and over all frames."""
    oracle = bench.score(lambda s: larynx_response(s.psi, s.fps, person_of(s)), CUES, 8, 30.0, 30.0, take=100)
    blind = bench.score(lambda s: larynx_response(s.psi, s.fps, dataclasses.replace(person_of(s),
                                                                                      swallow_amplitude=0.0)),
                        CUES, 8, 30.0, 30.0, take=100)
    assert set(oracle) == set(CUES)  # 8 people drawn over both kinds
    assert sum(r["people"] for r in oracle.values()) == 8
    for kind in CUES:
        assert oracle[kind]["rmse"] == pytest.approx(0.0005, rel=0.1)
        assert oracle[kind]["rmse_in_swallows"] == pytest.approx(0.0005, rel=0.2)
        assert blind[kind]["swallow_rms"] > 0.002  # the kind's people swallowed
        expected = np.hypot(blind[kind]["swallow_rms"], 0.0005)
        assert blind[kind]["rmse"] == pytest.approx(expected, rel=0.05)
        inside = np.hypot(blind[kind]["swallow_rms_in_swallows"], 0.0005)
        assert blind[kind]["rmse_in_swallows"] == pytest.approx(inside, rel=0.05)
        assert blind[kind]["swallow_rms_in_swallows"] > blind[kind]["swallow_rms"]
        assert blind[kind]["tau_std"] > blind[kind]["swallow_rms"] * 0.8


def test_the_cue_kinds_are_checked(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench_larynx_cues.py", "--checkpoint", "x.pt", "--cues", "seal,cough"])
    with pytest.raises(SystemExit):
        bench.main()
    assert f"--cues: unknown cough; expected some of {', '.join(SWALLOW_CUES)}" in capsys.readouterr().err


def test_a_checkpoint_trained_on_pairs_is_refused(monkeypatch):
    """Its people (s0, s1, ...) are not data=synthetic's, though the names may coincide."""
    monkeypatch.setattr(bench, "load_checkpoint", lambda path, task: {"config": {"data": {"kind": "pairs"}}})
    monkeypatch.setattr(sys, "argv", ["bench_larynx_cues.py", "--checkpoint", "run.pt"])
    with pytest.raises(SystemExit, match="run.pt: trained on data=pairs; this script scores data=synthetic's people"):
        bench.main()
