"""The voice moves the larynx: larynx height from the pitch (F0) of a take's audio, added to tau.

- :mod:`motion.voice.config`: :class:`VoiceConfig` (slope, knee, time constants; published defaults) and
  ``voice.json`` files; the units (Hz, semitones, mm, :data:`TAU_PER_MM`);
- :mod:`motion.voice.term`: the documented mapping F0 -> larynx height -> zero-mean tau (and how it shares
  the work with the expression-driven tau);
- :mod:`motion.voice.align`: a take's audio on the capture's frames (aligned at the start, durations checked);
- :mod:`motion.voice.fit`: the parameters fitted from pair files with F0 (``python -m data.pairs audio=``);
- :mod:`motion.voice.cli`: ``python -m motion.voice mode=fit pairs=DIR out=voice.json``.

Audio decoding and the F0 tracker (Praat through praat-parselmouth) are ``data.audio``'s.
"""

from data.audio import read_audio, track_f0
from motion.voice.align import check_durations, voice_on_frames
from motion.voice.config import DEFAULT_SLOPE, TAU_PER_MM, VoiceConfig, load_voice, save_voice
from motion.voice.term import VoiceTerm, analyse_voice, height_target, voice_height

__all__ = [
    "DEFAULT_SLOPE",
    "TAU_PER_MM",
    "VoiceConfig",
    "VoiceTerm",
    "analyse_voice",
    "check_durations",
    "height_target",
    "load_voice",
    "read_audio",
    "save_voice",
    "track_f0",
    "voice_height",
    "voice_on_frames",
]
