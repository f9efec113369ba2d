"""Helper threads that run the tasks of one call beside the caller (the rig engine's thread pool).

``WORKERS.run(task, count, threads)`` runs ``task(i)`` for every ``i < count`` on the calling thread and
``threads - 1`` helpers, each running torch single-threaded; a call hands out indices from a shared counter,
so the threads balance themselves and none waits for another except at the end of the call.
"""
from __future__ import annotations

import itertools
import os
import queue
import threading

import torch


def usable_cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


class _ChunkWorkers:
    """Helper threads that run whole chunks of a forward pass beside the caller.

    Each helper runs torch single-threaded (``torch.set_num_threads(1)`` is per thread for OpenMP and
    MKL); a call hands out chunk indices from a shared counter, so the threads balance themselves and
    none waits for another except at the end of the call.  Created on first use; a forked child starts
    without them and makes its own.
    """

    def __init__(self):
        self._reset()
        os.register_at_fork(after_in_child=self._reset)

    def _reset(self) -> None:
        self._threads: list[threading.Thread] = []
        self._jobs: queue.SimpleQueue = queue.SimpleQueue()
        self._lock = threading.Lock()

    def _grow(self, count: int) -> None:
        with self._lock:
            while len(self._threads) < count:
                ready = threading.Event()
                thread = threading.Thread(target=self._serve, args=(self._jobs, ready), daemon=True,
                                          name=f"hackneck-rig-{len(self._threads)}")
                thread.start()
                ready.wait()
                self._threads.append(thread)

    @staticmethod
    def _serve(jobs: queue.SimpleQueue, ready: threading.Event) -> None:
        torch.set_num_threads(1)  # also sets torch's default for new threads: the caller restores it
        ready.set()
        while True:
            jobs.get()()

    def run(self, task, count: int, threads: int) -> None:
        """``task(i)`` for every i < count on the calling thread and ``threads - 1`` helpers; the first
        exception is re-raised here.  Call under ``single_thread``."""
        helpers = min(threads, count) - 1
        if helpers <= 0:
            for i in range(count):
                task(i)
            return
        self._grow(helpers)
        indices = itertools.count()
        failures: list[BaseException] = []
        done = threading.Semaphore(0)
        inference = torch.is_inference_mode_enabled()

        def drain() -> None:
            while not failures:
                i = next(indices)
                if i >= count:
                    return
                try:
                    task(i)
                except BaseException as error:  # noqa: B036 - handed to the caller
                    failures.append(error)

        def helper() -> None:
            try:
                with torch.inference_mode(inference), torch.no_grad():
                    drain()
            finally:
                done.release()

        for _ in range(helpers):
            self._jobs.put(helper)
        drain()
        for _ in range(helpers):
            done.acquire()
        if failures:
            raise failures[0]


WORKERS = _ChunkWorkers()
