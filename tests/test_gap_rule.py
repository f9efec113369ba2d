"""The gap rule (base.timebase, docs/conventions.md "Gaps") on hand-computed takes: short gaps interpolated over,
long ones held at the last grid point before them, the recurrent model restarted after them."""
from __future__ import annotations

import numpy as np

import motion.pipeline.animate as animate
from base.timebase import GAP_SECONDS, fill_held, grid_segments, resample_held, resample_uniform


def test_long_gap_held_short_gap_interpolated():
    # 30 fps: frames at 0, 1/30, 2/30, a gap of 0.933 s, then 1.0 and 1 + 1/30; values 0, 1, 2, 10, 11
    time = np.array([0, 1, 2, 30, 31]) / 30
    values = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    grid, out = resample_held(time, values, 30.0)
    assert len(grid) == 32 and GAP_SECONDS == 0.25
    np.testing.assert_allclose(out, [0, 1, 2] + [2] * 27 + [10, 11])
    segment, held = grid_segments(time, 30.0)
    assert held.tolist() == [False] * 3 + [True] * 27 + [False] * 2 and segment[30] == segment[31] != segment[0]
    # 0.2 s apart (under GAP_SECONDS): interpolated, as resample_uniform does
    short = np.array([0.0, 0.2])
    np.testing.assert_allclose(resample_held(short, np.array([0.0, 6.0]), 30.0)[1], [0, 1, 2, 3, 4, 5, 6])
    np.testing.assert_allclose(resample_held(short, np.array([0.0, 6.0]), 30.0)[1],
                               resample_uniform(short, np.array([0.0, 6.0]), 30.0)[1])
    assert fill_held(np.array([5, 6, 7, 8]), np.array([False, True, True, False])).tolist() == [5, 5, 5, 8]


def test_recurrent_model_restarts_after_a_gap(monkeypatch):
    """segmented_tau: a stand-in recurrent model (tau = running sum of psi's first weight) restarts after the
    gap, and the gap's points hold the tau before it."""
    monkeypatch.setattr(animate, "predict_tau", lambda model, psi, subject=None: np.cumsum(psi[:, 0]))
    time = np.array([0, 1, 2, 30, 31]) / 30
    psi = np.zeros((5, 55), dtype=np.float32)
    psi[:, 0] = [1, 1, 1, 5, 5]
    _, uniform = resample_held(time, psi, 30.0)
    tau = animate.segmented_tau(None, uniform, *grid_segments(time, 30.0))
    np.testing.assert_allclose(tau, [1, 2, 3] + [3] * 27 + [5, 10])  # not 3 + 5 + ...: restarted
