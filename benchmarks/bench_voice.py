"""The voice (issue 45): speed of the audio stage of a one-minute take, and Praat against pYIN as F0 tracker.

    python benchmarks/bench_voice.py [--seconds 60] [--repeats 3] [--no-pyin]

1. Audio stage (what ``infer.py audio=`` adds): decode a one-minute take's sound (a 48 kHz AAC ``.mov``
   as Live Link Face writes, through ffmpeg; and the same as a ``.wav``), track F0 (Praat), the voice term,
   and put it on 60 fps frames.  Median wall seconds of ``--repeats`` runs.
2. Trackers: Praat's autocorrelation method (``data.audio.track_f0``, parselmouth) against librosa's pYIN
   (``librosa.pyin``, same 60-700 Hz range and 10 ms hop) on synthetic voices of known F0 (a glide with
   pauses, a sung vibrato, speech-like syllables), clean, with white noise at 20 and 10 dB SNR, and through
   AAC: the share of truly voiced frames within half a semitone (unvoiced counts as wrong), the share of
   silent frames called voiced, and seconds per minute of audio.  On espeak-ng speech (no truth) the two
   are compared with each other.

Needs ffmpeg and espeak-ng on PATH, praat-parselmouth, and librosa for the comparison (``--no-pyin`` skips it).
"""
from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.io import wavfile

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from data.audio import AudioTrack, read_audio, track_f0  # noqa: E402
from motion.voice import VoiceConfig, analyse_voice  # noqa: E402

RATE = 16000
TEXT = ("The quick brown fox jumps over the lazy dog. Is it raining in Berlin today? "
        "I never said she stole my money. Would you like a cup of tea, or rather coffee?")


def glide(t):
    return np.where((t % 1.0) < 0.8, 90 * 2 ** (np.abs(((t / 2) % 2) - 1)), 0.0)


def vibrato(t):
    return np.where((t % 3.0) < 2.6, 220 * 2 ** (np.sin(2 * np.pi * 5.5 * t) / 12), 0.0)


def speech_like(t):
    f = 250 * 2 ** ((4 * np.sin(2 * np.pi * 0.7 * t) - 1.5 * (t % 4) / 4 + 3 * np.sin(2 * np.pi * 2.1 * t)) / 12)
    return np.where(np.sin(2 * np.pi * 4 * t) > -0.5, f, 0.0)


def buzz(f0_at, seconds: float, snr_db: float | None, seed: int) -> np.ndarray:
    t = np.arange(int(seconds * RATE)) / RATE
    f0 = f0_at(t)
    phase = 2 * np.pi * np.cumsum(f0) / RATE
    voiced = 0.3 * np.where(f0 > 0, sum(np.sin(k * phase) / k * (k * f0 < 4000) for k in range(1, 30)), 0.0)
    rng = np.random.default_rng(seed)
    power = np.mean(voiced[f0 > 0] ** 2)
    noise_std = 1e-4 if snr_db is None else np.sqrt(power / 10 ** (snr_db / 10))
    return (voiced + noise_std * rng.standard_normal(len(t))).astype(np.float32)


def pyin(audio: AudioTrack) -> tuple[np.ndarray, np.ndarray]:
    import librosa

    hop = int(round(0.01 * audio.rate))
    f0, voiced, _ = librosa.pyin(audio.samples, fmin=60.0, fmax=700.0, sr=audio.rate, frame_length=4 * hop * 2,
                                 hop_length=hop, center=True)
    return np.arange(len(f0)) * hop / audio.rate, np.where(voiced & np.isfinite(f0), f0, 0.0)


def score(time: np.ndarray, f0: np.ndarray, truth_at) -> tuple[float, float]:
    window = np.stack([truth_at(time + d) for d in np.linspace(-0.025, 0.025, 11)])
    voiced, silent = (window > 0).all(axis=0), (window == 0).all(axis=0)
    truth = truth_at(time)
    with np.errstate(divide="ignore", invalid="ignore"):
        error = np.abs(12 * np.log2(f0[voiced] / truth[voiced]))
    hits = np.where(f0[voiced] > 0, error < 0.5, False)
    return float(hits.mean()), float((f0[silent] > 0).mean())


def through_aac(samples: np.ndarray, folder: Path) -> AudioTrack:
    wav, m4a = folder / "x.wav", folder / "x.m4a"
    wavfile.write(wav, RATE, (np.clip(samples, -1, 1) * 32767).astype(np.int16))
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-i", str(wav), "-c:a", "aac", "-b:a", "96k", str(m4a)], check=True)
    return read_audio(m4a)


def one_minute_take(folder: Path, seconds: float) -> tuple[Path, Path]:
    """espeak-ng speech of several voices and pitches, ``seconds`` long, as 48 kHz .wav and AAC .mov."""
    parts = []
    for k, (voice, pitch) in enumerate([("en", 40), ("en+f3", 60), ("de", 50), ("fr", 70)]):
        path = folder / f"part{k}.wav"
        subprocess.run(["espeak-ng", "-w", str(path), "-v", voice, "-p", str(pitch), TEXT], check=True)
        parts.append(str(path))
    listing = folder / "parts.txt"
    listing.write_text("".join(f"file '{p}'\n" for p in parts) * 20)
    wav, mov = folder / "take.wav", folder / "take.mov"
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-f", "concat", "-safe", "0", "-i", str(listing), "-t",
                    str(seconds), "-ar", "48000", str(wav)], check=True)
    subprocess.run(["ffmpeg", "-v", "error", "-y", "-f", "lavfi", "-i", f"color=size=64x64:rate=30:d={seconds}",
                    "-i", str(wav), "-shortest", "-c:v", "libx264", "-c:a", "aac", "-b:a", "128k", str(mov)],
                   check=True)
    return wav, mov


def audio_stage(path: Path, seconds: float) -> None:
    term = analyse_voice(read_audio(path), VoiceConfig())
    term.on_frames(np.arange(0, seconds, 1 / 60))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--no-pyin", action="store_true")
    args = parser.parse_args()
    for tool in ("ffmpeg", "espeak-ng"):
        if shutil.which(tool) is None:
            sys.exit(f"bench_voice: {tool} not on PATH")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        wav, mov = one_minute_take(folder, args.seconds)
        print(f"audio stage of a {args.seconds:g} s take (decode, Praat F0, voice term, 60 fps frames):")
        for path in (mov, wav):
            walls = []
            for _ in range(args.repeats):
                started = time.perf_counter()
                audio_stage(path, args.seconds)
                walls.append(time.perf_counter() - started)
            started = time.perf_counter()
            read_audio(path)
            decode = time.perf_counter() - started
            print(f"  {path.suffix}: {np.median(walls):.2f} s median of {args.repeats} (decode alone {decode:.2f} s)")
        trackers = {"praat": track_f0}
        if not args.no_pyin:
            trackers["pyin"] = pyin
        print("\nF0 trackers on voices of known F0 (20 s each): within 0.5 st of voiced frames / silence called "
              "voiced / s per audio minute")
        for name, truth_at in (("glide", glide), ("vibrato", vibrato), ("speech_like", speech_like)):
            for condition, snr in (("clean", None), ("20 dB", 20.0), ("10 dB", 10.0), ("AAC", None)):
                samples = buzz(truth_at, 20.0, snr, seed=7)
                audio = through_aac(samples, folder) if condition == "AAC" else AudioTrack(samples, RATE, name)
                row = []
                for tracker, run in trackers.items():
                    started = time.perf_counter()
                    t, f0 = run(audio)
                    spent = (time.perf_counter() - started) * 60.0 / audio.duration
                    hits, false_voiced = score(t, f0, truth_at)
                    row.append(f"{tracker} {hits:.3f} / {false_voiced:.3f} / {spent:.2f} s")
                print(f"  {name:<12} {condition:<6} " + "   ".join(row))
        if "pyin" in trackers:
            print("\nespeak-ng speech (48 kHz take, first 20 s): Praat against pYIN")
            audio = read_audio(wav)
            audio = AudioTrack(audio.samples[: 20 * audio.rate], audio.rate, str(wav))
            t1, p1 = track_f0(audio)
            t2, p2 = pyin(audio)
            p2 = np.interp(t1, t2, p2) * (np.interp(t1, t2, (p2 > 0).astype(float)) > 0.99)
            both = (p1 > 0) & (p2 > 0)
            agree = np.mean(np.abs(12 * np.log2(p1[both] / p2[both])) < 0.5)
            print(f"  voiced: praat {np.mean(p1 > 0):.3f}, pyin {np.mean(p2 > 0):.3f}, same decision "
                  f"{np.mean((p1 > 0) == (p2 > 0)):.3f}; on frames both voiced, within 0.5 st: {agree:.3f}")


if __name__ == "__main__":
    main()
