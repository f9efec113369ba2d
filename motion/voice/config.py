"""The voice term's parameters (:class:`VoiceConfig`), their published defaults, and ``voice.json`` files.

Units owned here: F0 in Hz (0 = unvoiced), pitch in semitones relative to the speaker's median F0 over
the take, larynx height in mm (+ = up), time constants in seconds, and :data:`TAU_PER_MM`, the larynx
slide per mm of height.
"""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass
from pathlib import Path

from base.errors import InputError, require_file
from base.files import write_text

# tau is in UV units of the larynx map; on the HACK template one unit is about 33 cm along the neck
# ("0.03 ~ 1 cm", models/rig/model.py; issue 45), so 1 mm of larynx height is 0.003 tau.
TAU_PER_MM = 0.003

# Larynx height against F0, MRI of three speakers: 19.4, 29.9 and 10.8 mm per octave (Hirai, Honda,
# Fujimoto & Shimada 1994, J. Acoust. Soc. Jpn. (E) 15(3)); their mean, 20.0 mm per octave, is 1.67 mm per
# semitone (the range 0.9-2.5 mm per semitone).
HIRAI_MM_PER_OCTAVE = (19.4, 29.9, 10.8)
DEFAULT_SLOPE = sum(HIRAI_MM_PER_OCTAVE) / len(HIRAI_MM_PER_OCTAVE) / 12.0

# Lowering is about 26% faster than raising (Kleiner, Hasner & Birkholz 2023, ultrasound, 23 speakers):
# the fall time constant is the rise's / 1.26.
FALL_SPEEDUP = 1.26


@dataclass
class VoiceConfig:
    """How F0 moves the larynx (``voice.json`` holds these; ``python -m motion.voice mode=fit`` fits them).

    - ``slope``: mm of larynx height per semitone of F0 (default: Hirai et al. 1994's mean, 1.67);
    - ``knee``: semitones above the speaker's median F0 where the rise flattens, and ``high_ratio`` the
      slope above it as a fraction of ``slope``: at high F0 the hyoid moves forward and the larynx height
      stays nearly constant, while in the low range the whole larynx lowers (Honda, Hirai, Masaki & Shimada
      1999); the knee's place (+4 semitones, about the top of a speaker's habitual speaking range) and the
      ratio 0.25 are our reading of that qualitative finding, not published numbers;
    - ``rise`` / ``fall``: first-order time constants (s) towards a higher / lower target; ``fall`` is
      ``rise / 1.26`` by default (Kleiner et al. 2023).  ``rise`` = 0.08 s is a chosen default (the term
      follows syllable-rate pitch movements, ~4-6 Hz); a fit replaces it;
    - ``hold``: seconds the last voiced height is held through an unvoiced stretch (a voiceless consonant)
      before the target relaxes to rest (0 mm, the height at the median F0);
    - ``floor`` / ``ceiling``: the F0 tracker's range (Hz).
    """

    slope: float = round(DEFAULT_SLOPE, 4)
    knee: float = 4.0
    high_ratio: float = 0.25
    rise: float = 0.08
    fall: float = round(0.08 / FALL_SPEEDUP, 4)
    hold: float = 0.15
    floor: float = 60.0
    ceiling: float = 700.0

    def __post_init__(self) -> None:
        for name in ("rise", "fall", "floor", "ceiling"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"{name}={getattr(self, name)}: expected a positive number")
        if self.hold < 0:
            raise ValueError(f"hold={self.hold}: expected seconds >= 0")
        if not 0 <= self.high_ratio <= 1:
            raise ValueError(f"high_ratio={self.high_ratio}: expected a fraction in [0, 1]")
        if self.ceiling <= self.floor:
            raise ValueError(f"ceiling={self.ceiling} must be above floor={self.floor} (Hz)")


def load_voice(path: str | os.PathLike | None, key: str = "voice") -> VoiceConfig:
    """The VoiceConfig in ``path`` (a ``voice.json``; keys it lacks keep their defaults); ``None`` or
    ``"default"``: the defaults.  InputError naming the file on unknown keys or bad values."""
    if path is None or str(path) == "default":
        return VoiceConfig()
    path = require_file(path, "voice parameters (.json)", key)
    try:
        values = json.loads(Path(path).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: not JSON ({e}); expected voice parameters from python -m motion.voice") from None
    if not isinstance(values, dict):
        raise InputError(f"{path}: expected a JSON object of voice parameters")
    values = values.get("voice", values)  # a fit's report holds them under "voice"
    known = {f.name for f in dataclasses.fields(VoiceConfig)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise InputError(f"{path}: unknown keys {unknown}; known: {sorted(known)}")
    try:
        return VoiceConfig(**{k: float(v) for k, v in values.items()})
    except (TypeError, ValueError) as e:
        raise InputError(f"{path}: {e}") from None


def save_voice(path: str | os.PathLike, voice: VoiceConfig, report: dict | None = None) -> None:
    """Write ``voice`` (and a fit's ``report``) as JSON, atomically."""
    payload = {"voice": dataclasses.asdict(voice), **({"fit": report} if report else {})}
    write_text(path, json.dumps(payload, indent=2, sort_keys=True) + "\n")
