"""A take's audio put on the capture's frames: aligned by their start, checked by their durations."""
from __future__ import annotations

import os

import numpy as np

from base.errors import InputError
from data.audio import read_audio
from motion.voice.config import VoiceConfig
from motion.voice.term import analyse_voice


def check_durations(audio_path: str, audio_seconds: float, capture: str, capture_seconds: float,
                    tolerance: float) -> None:
    """InputError naming both files when their durations differ by more than ``tolerance`` seconds."""
    if abs(audio_seconds - capture_seconds) > tolerance:
        relation = "shorter" if audio_seconds < capture_seconds else "longer"
        raise InputError(f"{audio_path}: {audio_seconds:.2f} s of audio is {relation} than the capture {capture} "
                         f"({capture_seconds:.2f} s); expected equal durations within audio_tolerance="
                         f"{tolerance:g} s (they are aligned at their start)")


def voice_on_frames(audio_path: str | os.PathLike, frame_time: np.ndarray, capture: str, capture_seconds: float,
                    voice: VoiceConfig, tolerance: float,
                    announce=print) -> tuple[np.ndarray, np.ndarray | None, dict]:
    """(f0 [T] Hz, tau_voice [T] or None, a summary) of ``audio_path`` at ``frame_time`` (s from the
    capture's start = the audio's start).  A file without voiced frames gives f0 = 0, no voice term and a
    note through ``announce``."""
    audio = read_audio(audio_path)
    check_durations(str(audio_path), audio.duration, capture, capture_seconds, tolerance)
    term = analyse_voice(audio, voice)
    if term is None:
        announce(f"{audio_path}: no voiced frames (silence or noise); no voice term, tau is the expressions' alone")
        return np.zeros(len(frame_time), np.float32), None, {"voiced": 0.0}
    f0, tau_voice = term.on_frames(frame_time)
    summary = {"voiced": float(np.mean(f0 > 0)), "median_f0_hz": round(term.reference_hz, 2),
               "tau_voice_range": float(np.ptp(tau_voice))}
    return f0, tau_voice, summary
