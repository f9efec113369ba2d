"""Wall-clock seconds per named stage of a run, for its report: ``with seconds.time("larynx"): ...``."""
from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager


class StageSeconds(dict):
    """{stage name: wall seconds}, in the order the stages first ran; a stage timed twice adds up."""

    @contextmanager
    def time(self, stage: str) -> Iterator[None]:
        """Time the ``with`` block as ``stage`` (also when it raises)."""
        started = time.perf_counter()
        try:
            yield
        finally:
            self[stage] = self.get(stage, 0.0) + time.perf_counter() - started
