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

from motion.voice.align import voice_on_frames
from motion.voice.config import VoiceConfig, load_voice
from motion.voice.term import analyse_voice, height_target

__all__ = ["VoiceConfig", "analyse_voice", "height_target", "load_voice", "voice_on_frames"]
