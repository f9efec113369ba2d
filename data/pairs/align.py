"""A tau track and an expression recording put on one clock and resampled into a pair (and the take's F0,
from its audio, on the pair's frames)."""
from __future__ import annotations

import numpy as np

from base.errors import InputError
from base.timebase import resample_uniform
from data.audio import AudioTrack, track_f0
from data.expressions import ExpressionTrack
from data.pairs.files import LarynxSequence
from data.tau_track import TauTrack


def align_pair(track: TauTrack, expressions: ExpressionTrack, fps: float | None = None, offset: float = 0.0,
               subject: str | None = None, name: str = "") -> tuple[LarynxSequence, np.ndarray]:
    """Align a tau track with an expression recording by time, resampled to ``fps`` on their overlap.

    ``offset`` (s) is added to the track's time.  ``fps`` defaults to the expression rate.
    Returns (the pair, its time [T] in seconds on the expression clock).
    """
    fps = float(expressions.fps if fps is None else fps)
    if not fps > 0:
        raise InputError(f"fps must be positive, got {fps}")
    track_time = track.time + offset
    start = max(track_time[0], expressions.time[0])
    stop = min(track_time[-1], expressions.time[-1])
    if stop - start < 1.0 / fps:
        raise InputError(
            f"{track.source} covers {track_time[0]:.3f}-{track_time[-1]:.3f} s (offset {offset:+g} s) and "
            f"{expressions.source} covers {expressions.time[0]:.3f}-{expressions.time[-1]:.3f} s: they overlap "
            f"by less than one frame at {fps:g} fps; check the files or give offset=<seconds>"
        )
    time, psi = resample_uniform(expressions.time, expressions.psi, fps, start, stop)
    _, tau = resample_uniform(track_time, track.tau, fps, start, stop)
    pair = LarynxSequence(psi.astype(np.float32), tau.astype(np.float32), fps, subject, name)
    return pair, time


def f0_on_pair(audio: AudioTrack, expressions: ExpressionTrack, time: np.ndarray, tolerance: float = 1.0) -> np.ndarray:
    """F0 [T] (Hz, 0 = unvoiced; ``data.audio.track_f0``) of ``audio`` at the pair's ``time`` (expression clock),
    the audio starting with the expression recording.  InputError naming both files when the audio ends more
    than ``tolerance`` s before the pair does."""
    needed = float(time[-1] - expressions.time[0])
    if audio.duration < needed - tolerance:
        raise InputError(f"{audio.source}: {audio.duration:.2f} s of audio, but the pair reaches {needed:.2f} s into "
                         f"{expressions.source}; expected audio covering the recording (aligned at its start)")
    analysis_time, f0 = track_f0(audio)
    if len(analysis_time) < 2:
        return np.zeros(len(time), np.float32)
    step = float(analysis_time[1] - analysis_time[0])
    at = time - expressions.time[0]
    nearest = np.clip(np.rint((at - analysis_time[0]) / step).astype(int), 0, len(f0) - 1)
    inside = (at >= analysis_time[0] - step / 2) & (at <= analysis_time[-1] + step / 2)
    return np.where(inside, f0[nearest], 0.0).astype(np.float32)
