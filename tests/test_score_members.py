"""Recombined ensembles (benchmarks/score_members.py): member k of an ensemble drawn from any run's member k."""
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import score_members  # noqa: E402

from base.errors import InputError  # noqa: E402


def run(members: np.ndarray, tau: np.ndarray) -> dict[str, np.ndarray]:
    return {"tau": tau, "member": members}


def test_identical_runs_recombine_to_their_own_score_with_no_spread():
    rng = np.random.default_rng(0)
    tau = rng.normal(size=(2, 50))
    members = tau + rng.normal(scale=0.1, size=(3, 2, 50))
    scores = score_members.recombined_rmse([run(members, tau), run(members.copy(), tau)], "member")
    assert scores.shape == (8,)
    np.testing.assert_allclose(scores, scores[0], rtol=1e-12)
    # the trimmed mean of three members is their median, frame by frame
    assert scores[0] == pytest.approx(np.sqrt(np.mean((np.median(members, 0) - tau) ** 2)), rel=1e-12)


def test_each_member_is_drawn_from_every_run():
    """Two runs of two members (the plain mean): run 1's members are off by +1 and +3, run 2's by -1 and +5;
    the four ensembles are off by 2, 3, 1 and 2 everywhere."""
    tau = np.zeros((1, 10))
    first = np.stack([tau + 1, tau + 3])
    second = np.stack([tau - 1, tau + 5])
    scores = score_members.recombined_rmse([run(first, tau), run(second, tau)], "member")
    assert sorted(scores.tolist()) == pytest.approx([1.0, 2.0, 2.0, 3.0])


def test_runs_of_other_takes_or_sizes_are_refused():
    tau = np.zeros((1, 10))
    with pytest.raises(InputError, match="different held-out tau"):
        score_members.recombined_rmse([run(np.zeros((3, 1, 10)), tau), run(np.zeros((3, 1, 10)), tau + 1)],
                                      "member")
    with pytest.raises(InputError, match=r"hold \[3, 2\] members"):
        score_members.recombined_rmse([run(np.zeros((3, 1, 10)), tau), run(np.zeros((2, 1, 10)), tau)], "member")


def test_a_file_without_members_is_named(tmp_path):
    path = tmp_path / "members_heldout.npz"
    np.savez(path, tau=np.zeros((1, 5)))
    with pytest.raises(InputError, match=r"members_heldout\.npz: no member; expected tau"):
        score_members.read_run(path)
    (tmp_path / "broken.npz").write_bytes(b"not a zip")
    with pytest.raises(InputError, match=r"broken\.npz: cannot read"):
        score_members.read_run(tmp_path / "broken.npz")


def test_a_folder_without_runs_is_named(tmp_path):
    with pytest.raises(InputError, match=r"results\.json: not found"):
        score_members.find_runs([tmp_path], None, 0)
    (tmp_path / "results.json").write_text("{}")
    with pytest.raises(InputError, match=r"no <family>/seed0/train<t>/members_heldout\.npz in .* for damped"):
        score_members.find_runs([tmp_path], "damped", 0)
