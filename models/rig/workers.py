"""The threads that run the tasks of one call beside the caller (the rig engine's thread pool).

``run_tasks(task, count, threads)`` runs ``task(i)`` for every ``i < count`` on the calling thread and
``threads - 1`` helpers of a ``concurrent.futures`` thread pool, each running torch single-threaded (the pool's
initializer); a call hands out indices from a shared counter, so the threads balance themselves and none waits
for another except at the end of the call.
"""
from __future__ import annotations

import itertools
import os
import threading
from concurrent.futures import ThreadPoolExecutor

import torch


def usable_cpus() -> int:
    """The CPUs this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover - not Linux
        return os.cpu_count() or 1


_POOL: tuple[ThreadPoolExecutor, int] | None = None  # (the pool, its helpers)
_POOL_LOCK = threading.Lock()


def _forget_pool() -> None:
    """A forked child inherits the pool but not its threads: it makes its own on first use."""
    global _POOL, _POOL_LOCK
    _POOL, _POOL_LOCK = None, threading.Lock()


os.register_at_fork(after_in_child=_forget_pool)


def _helpers(count: int) -> ThreadPoolExecutor:
    """The pool, made (or remade larger) to hold ``count`` helpers; its threads start on first use and run torch
    single-threaded (``torch.set_num_threads`` is per thread for OpenMP and MKL; it also sets torch's default for
    threads made later, which the caller, under ``single_thread``, restores)."""
    global _POOL
    with _POOL_LOCK:
        if _POOL is None or _POOL[1] < count:
            if _POOL is not None:
                _POOL[0].shutdown(wait=False)
            _POOL = (ThreadPoolExecutor(count, thread_name_prefix="hackneck-rig", initializer=torch.set_num_threads,
                                        initargs=(1,)), count)
        return _POOL[0]


def run_tasks(task, count: int, threads: int) -> None:
    """``task(i)`` for every i < count on the calling thread and ``threads - 1`` helpers; the first exception
    is re-raised here.  Call under ``single_thread``."""
    helpers = min(threads, count) - 1
    if helpers <= 0:
        for i in range(count):
            task(i)
        return
    indices = itertools.count()
    failures: list[BaseException] = []
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
        with torch.inference_mode(inference), torch.no_grad():
            drain()

    pool = _helpers(helpers)
    running = [pool.submit(helper) for _ in range(helpers)]
    drain()
    for future in running:
        future.result()
    if failures:
        raise failures[0]
