"""Progress of long loops: a tqdm bar on a terminal, a plain line now and then in logs and CI.

A bar redrawn in place is made for a terminal; written to a file (a log, a CI console) every redraw
becomes text, thousands of lines of it.  :func:`progress_bar` gives tqdm when standard error is a
terminal, and otherwise a :class:`LineProgress`, which prints one line every ``interval`` seconds and,
when it printed any, one at the end (a loop shorter than ``interval`` stays silent).  Both take the calls
the project's loops make: iteration, ``update``, ``set_postfix``, ``close`` and use as a context manager.
"""
from __future__ import annotations

import sys
import time
from collections.abc import Iterable, Iterator

from tqdm import tqdm


class LineProgress:
    """What tqdm shows, as a line every ``interval`` seconds (and at the end, after any) on standard error."""

    def __init__(self, iterable: Iterable | None = None, *, total: int | None = None, desc: str = "",
                 unit: str = "it", initial: int = 0, interval: float = 30.0, disable: bool = False, stream=None):
        self.iterable, self.desc, self.unit, self.interval, self.disable = iterable, desc, unit, interval, disable
        if total is None and hasattr(iterable, "__len__"):
            total = initial + len(iterable)
        self.total = total
        self.n, self.initial, self.postfix = initial, initial, ""
        self.stream = stream if stream is not None else sys.stderr
        self.started = self.last = time.perf_counter()
        self.closed, self.printed = False, 0

    def __iter__(self) -> Iterator:
        for item in self.iterable:
            yield item
            self.update(1)
        self.close()

    def __enter__(self) -> LineProgress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def set_postfix(self, values: dict | None = None, **kwargs) -> None:
        values = {**(values or {}), **kwargs}
        self.postfix = ", ".join(f"{k}={v}" for k, v in values.items())

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.perf_counter()
        if now - self.last >= self.interval:
            self.last = now
            self.print_line()

    def print_line(self) -> None:
        if self.disable:
            return
        elapsed = time.perf_counter() - self.started
        rate = (self.n - self.initial) / elapsed if elapsed > 0 else 0.0
        of = f"/{self.total}" if self.total is not None else ""
        line = f"{self.desc}: {self.n}{of} {self.unit} ({rate:.3g} {self.unit}/s, {elapsed:.0f} s)"
        print(line + (f" {self.postfix}" if self.postfix else ""), file=self.stream, flush=True)
        self.printed += 1

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            if self.printed:
                self.print_line()


def progress_bar(iterable: Iterable | None = None, *, total: int | None = None, desc: str = "", unit: str = "it",
                 initial: int = 0, disable: bool = False, interval: float = 30.0):
    """tqdm on a terminal (standard error a TTY), else a :class:`LineProgress` printing every ``interval`` s."""
    if sys.stderr.isatty():
        return tqdm(iterable, total=total, desc=desc, unit=unit, initial=initial, disable=disable,
                    dynamic_ncols=True)
    return LineProgress(iterable, total=total, desc=desc, unit=unit, initial=initial, interval=interval,
                        disable=disable)
