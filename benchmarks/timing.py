"""Timing shared by the benchmark scripts."""
from __future__ import annotations

import time

import numpy as np


def frames_per_second(run, frames: int, repeats: int, warmup: int = 3) -> tuple[float, float]:
    """(frames per wall-clock second, frames per CPU second of this process), medians over ``repeats``
    calls of ``run`` that each process ``frames`` frames.

    On a CPU shared with other jobs the wall clock also counts time the threads waited for a core;
    the CPU-time figure (divided by the thread count) is what idle cores would do.
    """
    for _ in range(warmup):
        run()
    wall, cpu = [], []
    for _ in range(repeats):
        start, start_cpu = time.perf_counter(), time.process_time()
        run()
        wall.append(time.perf_counter() - start)
        cpu.append(time.process_time() - start_cpu)
    return frames / float(np.median(wall)), frames / float(np.median(cpu))
