"""A sequence fitted as overlapping windows at once, one thread each, and the windows joined into one fit.

The fit's tensor and LAPACK work releases the GIL, so ``FitSettings.workers`` windows on as many threads (torch
at one intra-op thread) keep that many cores busy without a process's start-up.  A window's fit differs from
the whole sequence's only near its ends (the temporal term couples a frame to a few neighbours), so each
window's frames are kept up to the middle of its overlap with the next (``FitSettings.window_overlap``
frames).  eta, one number per sequence, is the windows' mean weighted by the frames each keeps; so is the
per-joint uncertainty.  Not for the shape offset (one per sequence): ``fit_shape`` fits in one window.
"""
from __future__ import annotations

import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import torch

from models.fit.settings import FitResult


def spans(frames: int, parts: int, overlap: int) -> list[tuple[int, int, int, int]]:
    """``parts`` windows over ``frames`` overlapping by ``overlap``: (start, stop, keep_start, keep_stop) each,
    the kept ranges tiling [0, frames).  Fewer windows when a window would hold fewer than 2 x ``overlap``
    frames of its own."""
    parts = max(1, min(parts, frames // max(1, 2 * overlap)))
    cuts = [round(k * frames / parts) for k in range(parts + 1)]
    half = overlap // 2
    return [(max(0, cuts[k] - half), min(frames, cuts[k + 1] + overlap - half), cuts[k], cuts[k + 1])
            for k in range(parts)]


def fit_in_windows(fit: Callable[[slice, Callable[[int], None] | None], FitResult], frames: int, parts: int,
                   overlap: int, progress: Callable[[int], None] | None = None) -> FitResult:
    """``fit(window, progress)`` on each of ``spans(frames, parts, overlap)`` on its own thread, joined."""
    started = time.perf_counter()
    windows = spans(frames, parts, overlap)
    done = [0] * len(windows)
    lock = threading.Lock()

    def window_progress(k: int) -> Callable[[int], None] | None:
        if progress is None:
            return None

        def report(count: int) -> None:
            with lock:   # a frame counts once it is done in the window that keeps it (progress stays monotone)
                start, stop, keep_start, keep_stop = windows[k]
                done[k] = max(done[k], round(count * (keep_stop - keep_start) / (stop - start)))
                progress(sum(done))
        return report

    if len(windows) == 1:
        return fit(slice(0, frames), progress)
    threads = torch.get_num_threads()
    torch.set_num_threads(1)   # the windows are the parallelism (intra-op threads on top oversubscribe the cores)
    try:
        with ThreadPoolExecutor(len(windows)) as pool:
            futures = [pool.submit(fit, slice(start, stop), window_progress(k))
                       for k, (start, stop, _, _) in enumerate(windows)]
            results = [f.result() for f in futures]
    finally:
        torch.set_num_threads(threads)
    joined = join(results, windows)
    joined.report.update(seconds=time.perf_counter() - started,
                         frames_per_second=frames / max(time.perf_counter() - started, 1e-9))
    if progress is not None:
        progress(frames)
    return joined


def join(results: list[FitResult], windows: list[tuple[int, int, int, int]]) -> FitResult:
    """The windows' kept frames in order (see the module docstring for eta and the uncertainty)."""
    keep = [slice(keep_start - start, keep_stop - start) for start, _, keep_start, keep_stop in windows]
    counts = np.array([k.stop - k.start for k in keep], float)
    share = counts / counts.sum()

    def cat(name: str) -> np.ndarray:
        return np.concatenate([getattr(r, name)[k] for r, k in zip(results, keep)])

    rms = cat("fit_rms_mm")
    report = {"windows": [{"frames": [w[0], w[1]], "kept": [w[2], w[3]], **r.report}
                          for w, r in zip(windows, results)],
              "worst_frames": [int(i) for i in np.argsort(-rms)[: min(5, len(rms))]]}
    return FitResult(
        theta=cat("theta"), psi=cat("psi"), tau=cat("tau"), eta=float(share @ [r.eta for r in results]),
        root_rotation=cat("root_rotation"), root_translation=cat("root_translation"), shape_offset=None,
        fit_rms_mm=rms,
        joint_uncertainty_deg=(share @ np.stack([r.joint_uncertainty_deg for r in results])).astype(np.float32),
        report=report)
