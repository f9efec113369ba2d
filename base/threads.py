"""Torch's intra-op thread count, set for a block of code."""
from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def single_thread() -> Iterator[None]:
    """Run torch ops on the calling thread single-threaded inside the block (no OpenMP regions; the setting is
    restored after).

    For work made of many small operations (a live decoding step, a vertex chunk handed to a thread of our own):
    intra-op parallelism cannot speed them up, it only adds synchronisation, which stalls for milliseconds when
    another process holds the other core.  Nothing is changed when torch already runs one thread (setting it
    is not free) or inside ``torch.compile`` tracing.
    """
    threads = torch.get_num_threads()
    if threads == 1 or torch.compiler.is_compiling():
        yield
        return
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)
