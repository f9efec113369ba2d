"""The voice term: larynx height from the F0 contour of a take, and its share of tau.

The documented mapping, step by step, for F0 samples ``f0 [M]`` (Hz, 0 = unvoiced) every ``dt`` seconds:

1. reference: the median F0 over the take's voiced frames (the speaker's own centre, Hz);
2. pitch: ``s = 12 log2(f0 / reference)`` semitones on voiced frames;
3. height target (mm, + = up): ``slope * s`` up to ``knee`` semitones, ``slope * (knee + high_ratio *
   (s - knee))`` above it (flattened in the high range, Honda et al. 1999; linear down into the low range);
4. unvoiced frames: the last voiced target is held for ``hold`` seconds, then the target is 0 mm (rest,
   the height at the median F0); before the first voiced frame it is 0;
5. dynamics: a first-order lag towards the target, ``y += (1 - exp(-dt / T)) (target - y)`` with
   ``T = rise`` while the target is above ``y`` and ``T = fall`` while below (lowering ~26% faster,
   Kleiner et al. 2023); ``y`` starts at 0;
6. on the output frames: ``y`` linearly interpolated, times :data:`TAU_PER_MM`, minus its mean over the
   take's frames: **the voice term is zero-mean over the take by construction**.

How the voice term and the expression-driven tau share the work: the expression -> larynx model predicts
tau from the face (jaw, lips: rounded vowels lower the larynx, Hoole & Kroos 1998; swallows; the take's
posture), and the face does not show F0.  The voice term adds only what pitch carries: height deviations
from the speaker's median pitch, zero-mean over the take, so the take's level stays the expression
model's.  No double counting to the extent the expressions carry no F0; a fit from paired data
(``motion.voice.fit``) is made on what the expression model leaves (``checkpoint=`` the model in use), so
the fitted slope is only what pitch adds.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from data.audio import AudioTrack, track_f0
from motion.voice.config import TAU_PER_MM, VoiceConfig


def reference_hz(f0: np.ndarray) -> float | None:
    """The median F0 (Hz) over voiced samples (f0 > 0); None when nothing is voiced."""
    voiced = f0[f0 > 0]
    return float(np.median(voiced)) if len(voiced) else None


def semitones(f0: np.ndarray, reference: float) -> np.ndarray:
    """Semitones of ``f0`` relative to ``reference`` Hz; NaN where unvoiced."""
    out = np.full(len(f0), np.nan)
    voiced = f0 > 0
    out[voiced] = 12.0 * np.log2(f0[voiced] / reference)
    return out


def height_target(pitch: np.ndarray, voice: VoiceConfig) -> np.ndarray:
    """Target larynx height (mm) for pitch in semitones (step 3 of the mapping); NaN stays NaN."""
    above = np.maximum(pitch - voice.knee, 0.0)
    return voice.slope * (np.minimum(pitch, voice.knee) + voice.high_ratio * above)


def held_targets(target: np.ndarray, dt: float, hold: float) -> np.ndarray:
    """Step 4: NaN (unvoiced) targets replaced by the last voiced one for ``hold`` seconds, then by 0."""
    out = np.zeros(len(target))
    voiced = np.isfinite(target)
    if not voiced.any():
        return out
    index = np.where(voiced, np.arange(len(target)), -1)
    last = np.maximum.accumulate(index)                      # the last voiced sample at or before each
    held = (last >= 0) & ((np.arange(len(target)) - last) * dt <= hold + 1e-9)
    out[held] = target[last[held]]
    return out


def lag(target: np.ndarray, dt: float, rise: float, fall: float) -> np.ndarray:
    """Step 5: the asymmetric first-order lag of ``target`` (starting at 0)."""
    up, down = 1.0 - np.exp(-dt / rise), 1.0 - np.exp(-dt / fall)
    out = np.empty(len(target))
    y = 0.0
    for i, goal in enumerate(target.tolist()):
        y += (up if goal > y else down) * (goal - y)
        out[i] = y
    return out


def voice_height(f0: np.ndarray, dt: float, voice: VoiceConfig) -> np.ndarray | None:
    """Larynx height (mm, steps 1-5) for F0 samples every ``dt`` s; None when nothing is voiced."""
    f0 = np.asarray(f0, dtype=np.float64)
    reference = reference_hz(f0)
    if reference is None:
        return None
    target = held_targets(height_target(semitones(f0, reference), voice), dt, voice.hold)
    return lag(target, dt, voice.rise, voice.fall)


@dataclass
class VoiceTerm:
    """A take's voice analysis: F0 (Hz, 0 unvoiced) and larynx height (mm) at ``time`` (s, audio clock)."""

    time: np.ndarray
    f0: np.ndarray
    height_mm: np.ndarray
    reference_hz: float
    source: str

    def on_frames(self, frame_time: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(f0 [T] Hz, nearest analysis frame, 0 outside it; tau_voice [T], step 6: zero-mean) at
        ``frame_time`` (s on the audio clock)."""
        frame_time = np.asarray(frame_time, dtype=np.float64)
        step = float(self.time[1] - self.time[0]) if len(self.time) > 1 else 1.0
        nearest = np.clip(np.rint((frame_time - self.time[0]) / step).astype(int), 0, len(self.time) - 1)
        inside = (frame_time >= self.time[0] - step / 2) & (frame_time <= self.time[-1] + step / 2)
        f0 = np.where(inside, self.f0[nearest], 0.0)
        tau = np.interp(frame_time, self.time, self.height_mm) * TAU_PER_MM
        return f0.astype(np.float32), (tau - tau.mean()).astype(np.float32)


def analyse_voice(audio: AudioTrack, voice: VoiceConfig) -> VoiceTerm | None:
    """F0 and the larynx height of ``audio``; None when no frame is voiced (silence, noise)."""
    time, f0 = track_f0(audio, floor=voice.floor, ceiling=voice.ceiling)
    if len(time) < 2:
        return None
    height = voice_height(f0, float(time[1] - time[0]), voice)
    if height is None:
        return None
    return VoiceTerm(time, f0, height, float(reference_hz(f0)), audio.source)
