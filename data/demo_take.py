"""The built-in demo take: a face talking, blinking, turning and nodding, generated in code.

``python infer.py`` with no ``expressions=`` runs it, so a fresh clone shows the product with no
download.  It is an :class:`~data.expressions.ExpressionTrack` like any capture: 55 expression weights
and the head's yaw, pitch and roll (radians, ``motion.head2neck``'s convention) at ``fps``, and the
onset of a pause in speech where the demo plays a swallow (:data:`SWALLOW_ONSET`).

Timeline (s): 0-4 speech facing the camera; 4-6 a turn towards the subject's left (yaw up to 35 deg)
and back while talking; 6.2 a swallow in a pause; 8-9.5 a nod (pitch up to 20 deg); 9.5-12 speech
with a tilt to the right (roll up to 12 deg).
"""
from __future__ import annotations

import numpy as np

from data.expressions import EXPRESSION_NAMES, ExpressionTrack

DURATION = 12.0
DEMO_SOURCE = "built-in demo take"  # the track's source, as a file's path names a capture
SWALLOW_ONSET = 6.2
PAUSE = (6.0, 8.0)  # seconds without speech: the swallow's window

# Visemes as weights of a few mouth shapes (a rough open / round / closed / spread cycle of speech).
VISEMES = (
    {"jawOpen": 0.45, "mouthLowerDown_L": 0.3, "mouthLowerDown_R": 0.3},
    {"jawOpen": 0.2, "mouthFunnel": 0.5, "mouthPucker": 0.4},
    {"mouthClose": 0.35, "mouthPress_L": 0.3, "mouthPress_R": 0.3},
    {"jawOpen": 0.25, "mouthStretch_L": 0.35, "mouthStretch_R": 0.35, "mouthSmile_L": 0.2, "mouthSmile_R": 0.2},
)


def _bump(time: np.ndarray, start: float, stop: float) -> np.ndarray:
    """A raised-cosine bump from 0 at ``start`` to 1 halfway and back to 0 at ``stop``."""
    phase = np.clip((time - start) / (stop - start), 0.0, 1.0)
    return 0.5 - 0.5 * np.cos(2 * np.pi * phase)


def demo_take(fps: float = 30.0, seed: int = 0) -> ExpressionTrack:
    """The demo take at ``fps`` (frames per second), drawn from ``seed``.

    Returns an ExpressionTrack: psi [T,55], time [T] s, head_ypr [T,3] radians, T = 12 s * fps.
    """
    rng = np.random.default_rng(seed)
    time = np.arange(int(round(DURATION * fps))) / fps
    index = {name: k for k, name in enumerate(EXPRESSION_NAMES)}
    psi = np.zeros((len(time), len(EXPRESSION_NAMES)))
    talking = ~((time >= PAUSE[0]) & (time < PAUSE[1]))
    # Syllables at 3.5-5 per second, each a viseme with a smooth envelope.
    onset = 0.0
    while onset < DURATION:
        length = rng.uniform(0.2, 0.3)
        weight = _bump(time, onset, onset + length) * rng.uniform(0.6, 1.0)
        for name, value in VISEMES[rng.integers(len(VISEMES))].items():
            psi[:, index[name]] += value * weight * talking
        onset += length * rng.uniform(0.85, 1.0)
    for blink in np.sort(rng.uniform(0.5, DURATION - 0.5, size=5)):  # blinks last ~0.15 s
        closed = _bump(time, blink, blink + 0.15)
        psi[:, index["eyeBlink_L"]] += closed
        psi[:, index["eyeBlink_R"]] += closed
    psi[:, index["browInnerUp_L"]] += 0.2 * _bump(time, 4.0, 6.0)
    psi[:, index["browInnerUp_R"]] += 0.2 * _bump(time, 4.0, 6.0)
    psi += rng.normal(0.0, 0.005, psi.shape) * talking[:, None]  # tracker jitter
    psi = np.clip(psi, 0.0, 1.0)
    head = np.zeros((len(time), 3))
    head[:, 0] = np.radians(35.0) * _bump(time, 4.0, 6.0)    # yaw: a turn to the subject's left and back
    head[:, 1] = np.radians(20.0) * _bump(time, 8.0, 9.5)    # pitch: a nod
    head[:, 2] = np.radians(12.0) * _bump(time, 9.5, 12.0)   # roll: a tilt to the right shoulder
    head += np.radians(0.3) * np.sin(2 * np.pi * 0.7 * time)[:, None] * rng.normal(size=3)  # sway
    return ExpressionTrack(psi.astype(np.float32), time, float(fps), head, [], DEMO_SOURCE)
