"""The tracker's baseline: the plain estimate the larynx tracker (``motion.track``) is measured against
(``bench_tracker.py``, ``tests/test_track.py``)."""
from __future__ import annotations

import cv2
import numpy as np

from motion.track.kernel import LarynxKernel


def raw_correlation_argmax(normals: np.ndarray, kernel: LarynxKernel) -> tuple[float, float]:
    """The plain estimate: integer arg-max over the whole frame of the raw correlation k * N (TM_CCORR)."""
    scores = cv2.matchTemplate(np.asarray(normals, np.float32), kernel.normals, cv2.TM_CCORR)
    _, _, _, (col, row) = cv2.minMaxLoc(scores)
    return col + kernel.centre[0], row + kernel.centre[1]
