"""The real-regime benchmark's account of where the error lies (benchmarks/bench_larynx_real.py):
its swallow frames are where the swallow moves tau, and nowhere else."""
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import bench_larynx_real as bench  # noqa: E402

from data.pairs import LarynxSequence  # noqa: E402


def closing_jaw(open_frames: int = 60, frames: int = 300) -> np.ndarray:
    """psi [frames,55]: the jaw open (0.5) for ``open_frames`` frames, then closed; all else at rest."""
    psi = np.zeros((frames, 55), np.float32)
    psi[:open_frames, bench.K["jawOpen"]] = 0.5
    return psi


def test_swallow_frames_follow_the_cue_and_the_duration():
    """Subject family: a swallow starts once the jaw has been closed 0.3 s (9 frames at 30 fps) and lasts
    0.7 + 2 tau_a seconds; the frames marked are inside that span and fill most of it."""
    psi = closing_jaw()
    for subject in range(3):
        p = bench.person("subject", subject, seed=0, terms=5)
        mask = bench.swallow_frames("subject", psi, subject, seed=0)
        onset = 60 + 9 - 1  # the first frame where the closure has held 9 frames
        end = onset + int(np.ceil((0.7 + 2 * p.tau_a) * bench.FPS))
        assert not mask[:onset].any() and not mask[end + 1:].any(), (subject, np.flatnonzero(mask)[[0, -1]])
        assert mask[onset:end + 1].mean() > 0.8, (subject, mask[onset:end + 1].mean())


def test_no_swallow_while_the_jaw_stays_open():
    psi = closing_jaw(open_frames=300)
    assert not bench.swallow_frames("damped", psi, 0, seed=1).any()


def test_split_rmse_puts_each_error_on_its_side():
    tau = np.zeros(10, np.float32)
    sequence = LarynxSequence(np.zeros((10, 55), np.float32), tau, 30.0, "s0", "a")
    mask = np.arange(10) < 4
    prediction = np.where(mask, 0.02, 0.005)
    inside, outside = bench.split_rmse([prediction], [sequence], [mask])
    assert abs(inside - 0.02) < 1e-9 and abs(outside - 0.005) < 1e-9
