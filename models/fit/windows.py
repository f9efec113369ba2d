"""A sequence fitted as overlapping windows at once, one process each, and the windows joined into one fit.

``FitSettings.workers`` windows run in as many forked processes (torch at one intra-op thread each; a fork
shares the rig and the capture without copying or pickling them, and costs no start-up): threads were
measured slower than one window under the shared machine's load (the GIL's hand-overs between hundreds of
short tensor operations a chunk), and torch's intra-op threads cost several times the CPU (benchmarks/README.md,
"Fitting HACK to captures").  A window's fit differs from the whole sequence's only near its ends (the temporal
term couples a frame to a few neighbours), so each window's frames are kept up to the middle of its overlap
with the next (``FitSettings.window_overlap`` frames).  eta, one number per sequence, is the windows' mean
weighted by the frames each keeps; so is the per-joint uncertainty.  Not for the shape offset (one per
sequence): ``fit_shape`` fits in one window.
"""
from __future__ import annotations

import multiprocessing
import time
from collections.abc import Callable
from multiprocessing.connection import wait

import numpy as np
import torch

from models.fit.settings import FitResult

Window = tuple[int, int, int, int]   # start, stop, keep_start, keep_stop


def spans(frames: int, parts: int, overlap: int) -> list[Window]:
    """``parts`` windows over ``frames`` overlapping by ``overlap``: (start, stop, keep_start, keep_stop) each,
    the kept ranges tiling [0, frames).  Fewer windows when a window would hold fewer than 2 x ``overlap``
    frames of its own."""
    parts = max(1, min(parts, frames // max(1, 2 * overlap)))
    cuts = [round(k * frames / parts) for k in range(parts + 1)]
    half = overlap // 2
    return [(max(0, cuts[k] - half), min(frames, cuts[k + 1] + overlap - half), cuts[k], cuts[k + 1])
            for k in range(parts)]


def _fit_window(fit: Callable, window: Window, done, k: int, connection) -> None:
    """In a forked worker: ``fit`` on one window; its result (or its error) back through ``connection``, and
    the frames it keeps that are done so far in ``done[k]``."""
    start, stop, keep_start, keep_stop = window
    torch.set_num_threads(1)

    def report(count: int) -> None:
        done[k] = round(count * (keep_stop - keep_start) / (stop - start))
    try:
        connection.send((True, fit(slice(start, stop), report)))
    except BaseException as error:   # noqa: BLE001 - handed to the parent, which raises it
        connection.send((False, error))
    finally:
        connection.close()


def fit_in_windows(fit: Callable[[slice, Callable[[int], None] | None], FitResult], frames: int, parts: int,
                   overlap: int, progress: Callable[[int], None] | None = None) -> FitResult:
    """``fit(window, progress)`` on each of ``spans(frames, parts, overlap)`` in its own forked process, joined;
    an error in a window is raised here."""
    started = time.perf_counter()
    windows = spans(frames, parts, overlap)
    if len(windows) == 1:
        return fit(slice(0, frames), progress)
    context = multiprocessing.get_context("fork")
    done = context.Array("i", len(windows), lock=False)
    workers, pending = [], {}
    for k, window in enumerate(windows):
        receive, send = context.Pipe(duplex=False)
        worker = context.Process(target=_fit_window, args=(fit, window, done, k, send), daemon=True)
        worker.start()
        send.close()
        workers.append(worker)
        pending[receive] = k
    results: list[FitResult | None] = [None] * len(windows)
    try:
        while pending:
            for connection in wait(list(pending), timeout=0.5):
                k = pending.pop(connection)
                ok, value = connection.recv()
                if not ok:
                    raise value
                results[k] = value
            if progress is not None:
                progress(sum(done))
    finally:
        for worker in workers:
            if worker.is_alive() and pending:
                worker.terminate()
            worker.join()
    joined = join(results, windows)
    joined.report.update(seconds=time.perf_counter() - started,
                         frames_per_second=frames / max(time.perf_counter() - started, 1e-9))
    if progress is not None:
        progress(frames)
    return joined


def join(results: list[FitResult], windows: list[Window]) -> FitResult:
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
