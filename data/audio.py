"""Audio of a take: decoded to mono float PCM, and its fundamental frequency (F0) per analysis frame.

- :func:`read_audio`: ``.wav`` read directly (``scipy.io.wavfile``); anything else (``.mov``, ``.mp4``,
  ``.m4a``, ``.mp3``, a WAV scipy cannot read, ...) decoded by the ``ffmpeg`` executable (Debian package
  ``ffmpeg``) at the file's own rate.  Channels are averaged; samples are float32 in [-1, 1].
- :func:`track_f0`: F0 in Hz per analysis frame with a voiced/unvoiced decision (0 = unvoiced), from
  Praat's autocorrelation pitch tracker (Boersma 1993) through ``praat-parselmouth``.

The tracker lives here, in the data layer, so that ``python -m data.pairs audio=...`` can store F0 in a
pair file; what F0 does to the larynx is ``motion.voice``'s.  Praat was chosen over librosa's pYIN after
measuring both (``benchmarks/bench_voice.py``, figures in benchmarks/README.md): on synthetic voices of
known F0, clean, at 10 dB SNR and through AAC, both put >= 0.986 of voiced frames within half a semitone,
but pYIN called 6-52% of silent frames voiced (Praat none) and took 11-24 s per minute of audio (Praat
0.13-0.33 s).

Bad input (no file, not decodable, no audio stream, a rate below :data:`MIN_RATE`) raises
``base.errors.InputError`` naming the file and what was expected.
"""
from __future__ import annotations

import json
import os
import shutil
import subprocess
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError, require_file

MIN_RATE = 8000            # Hz: below it speech F0 tracking is unreliable (telephone band is 8 kHz)
AUDIO_SUFFIXES = (".wav", ".mov", ".mp4", ".m4a", ".mp3", ".flac", ".ogg", ".aac", ".mkv", ".webm")
F0_STEP = 0.01             # s between analysis frames (100 Hz)
F0_FLOOR = 60.0            # Hz: lowest F0 tracked (low male speech ~ 70 Hz)
F0_CEILING = 700.0         # Hz: highest F0 tracked (high female / child speech, sung notes to F5)


@dataclass
class AudioTrack:
    """Mono audio: samples [N] float32 in [-1, 1] at ``rate`` Hz, time 0 = the file's first sample."""

    samples: np.ndarray
    rate: int
    source: str

    @property
    def duration(self) -> float:
        """Seconds of audio."""
        return len(self.samples) / float(self.rate)


def _to_float(data: np.ndarray) -> np.ndarray:
    """Integer or float PCM [N] or [N,C] as mono float32 in [-1, 1]."""
    if data.dtype.kind == "u":  # 8-bit WAV is unsigned, centred on 128
        bits = 8 * data.dtype.itemsize
        data = (data.astype(np.float64) - 2 ** (bits - 1)) / 2 ** (bits - 1)
    elif data.dtype.kind == "i":
        data = data.astype(np.float64) / float(2 ** (8 * data.dtype.itemsize - 1))
    else:
        data = data.astype(np.float64)
    if data.ndim == 2:
        data = data.mean(axis=1)
    return data.astype(np.float32)


def _ffmpeg(path: Path, what: str, wav_error: Exception | None = None) -> tuple[str, str]:
    """The ffmpeg and ffprobe executables; InputError without them (``wav_error``: why scipy could not read the
    .wav that needed them)."""
    ffmpeg, ffprobe = shutil.which("ffmpeg"), shutil.which("ffprobe")
    if ffmpeg is None or ffprobe is None:
        if wav_error is not None:
            raise InputError(f"{path}: not a readable audio file as PCM WAV ({wav_error}); a WAV in another codec "
                             f"needs the ffmpeg and ffprobe executables (Debian package ffmpeg), which are not on PATH")
        raise InputError(f"{path}: decoding {what} needs the ffmpeg and ffprobe executables (Debian package "
                         f"ffmpeg), which are not on PATH; install ffmpeg or give a .wav file")
    return ffmpeg, ffprobe


def _file_argument(path: Path) -> str:
    """``path`` as ffmpeg / ffprobe must be given it: absolute, so that a file named ``-y.mp4`` or ``-report``
    is a file and not an option, and ``a:b.mov`` not a protocol (both read a leading ``-`` or ``name:`` so)."""
    return os.path.abspath(path)


def _decode(path: Path, wav_error: Exception | None = None) -> tuple[np.ndarray, int]:
    """Samples and rate of the first audio stream of ``path`` through ffmpeg (``wav_error``: see :func:`_ffmpeg`)."""
    ffmpeg, ffprobe = _ffmpeg(path, f"'{path.suffix}' audio", wav_error)
    probe = subprocess.run([ffprobe, "-v", "error", "-select_streams", "a:0", "-show_entries",
                            "stream=sample_rate,channels", "-of", "json", _file_argument(path)],
                           capture_output=True, text=True)
    if probe.returncode != 0:
        reason = (probe.stderr.strip().splitlines() or ["unknown format"])[-1]
        raise InputError(f"{path}: not a readable audio or video file ({reason}); expected a .wav, .mov or .mp4 "
                         f"with a sound track")
    streams = json.loads(probe.stdout or "{}").get("streams", [])
    if not streams:
        raise InputError(f"{path}: no audio stream; expected a file with a sound track")
    rate = int(float(streams[0].get("sample_rate", 0)))
    _check_rate(path, rate)
    decoded = subprocess.run([ffmpeg, "-nostdin", "-v", "error", "-i", _file_argument(path), "-map", "0:a:0", "-vn",
                              "-ac", "1", "-f", "f32le", "-acodec", "pcm_f32le", "-"], capture_output=True)
    if decoded.returncode != 0:
        reason = (decoded.stderr.decode(errors="replace").strip().splitlines() or ["ffmpeg failed"])[-1]
        raise InputError(f"{path}: the sound track could not be decoded ({reason})")
    return np.frombuffer(decoded.stdout, dtype="<f4").astype(np.float32), rate


def _check_rate(path: Path, rate: int) -> None:
    if rate < MIN_RATE:
        raise InputError(f"{path}: sample rate {rate} Hz, expected at least {MIN_RATE} Hz")


def read_audio(path: str | os.PathLike, key: str = "audio") -> AudioTrack:
    """The mono audio of ``path`` (``key`` is the config key that named it, for the error messages)."""
    path = require_file(path, "audio file", key)
    samples, wav_error = None, None
    if path.suffix.lower() == ".wav":
        from scipy.io import wavfile

        try:
            with open(path, "rb") as f:
                rate, data = wavfile.read(f)
            samples = _to_float(np.asarray(data))
        except (ValueError, OSError, EOFError) as e:
            wav_error = e  # a WAV codec scipy does not know (ADPCM, ...), or not a WAV: ffmpeg decides
        else:
            _check_rate(path, int(rate))
    if samples is None:
        samples, rate = _decode(path, wav_error)
    if len(samples) == 0:
        raise InputError(f"{path}: the sound track is empty; expected audio")
    if not np.isfinite(samples).all():
        raise InputError(f"{path}: non-finite audio samples; expected PCM audio")
    return AudioTrack(np.ascontiguousarray(samples, dtype=np.float32), int(rate), str(path))


def track_f0(audio: AudioTrack, step: float = F0_STEP, floor: float = F0_FLOOR,
             ceiling: float = F0_CEILING) -> tuple[np.ndarray, np.ndarray]:
    """(time [M] s, f0 [M] Hz with 0 where unvoiced) at ``step`` s, Praat's autocorrelation method.

    Praat's defaults otherwise (voicing threshold 0.45, silence threshold 0.03, octave cost 0.01,
    octave-jump cost 0.35, voiced/unvoiced cost 0.14).  Needs ``praat-parselmouth``.
    """
    try:
        import parselmouth
    except ImportError:
        raise InputError(f"{audio.source}: F0 tracking needs the package praat-parselmouth "
                         f"(pip install praat-parselmouth==0.4.7)") from None
    if audio.duration < 3.0 / floor:  # Praat needs three periods of the floor in a window
        return np.zeros(0), np.zeros(0)
    sound = parselmouth.Sound(audio.samples.astype(np.float64), sampling_frequency=float(audio.rate))
    pitch = sound.to_pitch_ac(time_step=step, pitch_floor=floor, pitch_ceiling=ceiling)
    f0 = np.asarray(pitch.selected_array["frequency"], dtype=np.float64)
    f0[~np.isfinite(f0)] = 0.0
    return np.asarray(pitch.xs(), dtype=np.float64), f0


def has_sound(path: Path) -> bool:
    """Whether ``path`` (a video or audio file) has an audio stream; True when ffprobe is missing (reading it
    then says what is needed)."""
    ffprobe = shutil.which("ffprobe")
    if path.suffix.lower() == ".wav" or ffprobe is None:
        return True
    probe = subprocess.run([ffprobe, "-v", "error", "-select_streams", "a", "-show_entries", "stream=index", "-of",
                            "csv=p=0", _file_argument(path)], capture_output=True, text=True)
    return probe.returncode == 0 and bool(probe.stdout.strip())


def find_audio_beside(take: str | os.PathLike) -> Path | None:
    """The audio file beside ``take`` with the same stem (``take.wav``, ``take.mov``, ...), the take itself if
    it is a video or audio file, or None."""
    take = Path(take)
    if take.suffix.lower() in AUDIO_SUFFIXES:
        return take if has_sound(take) else None
    for suffix in AUDIO_SUFFIXES:
        for candidate in (take.with_suffix(suffix), take.with_suffix(suffix.upper())):
            if candidate.is_file():
                return candidate
    return None
