"""``python -m motion.voice``: fit the voice term's parameters from pair files with F0, for ``infer.py voice=``.

    python -m data.pairs track=track.csv expressions=take.csv audio=take.mov out=pairs/take1.npz
    python -m motion.voice mode=fit pairs=pairs/ out=voice.json [checkpoint=default|none|<larynx ckpt>] \\
        [subject=..] [voice.knee=4] [voice.high_ratio=0.25] [voice.hold=0.15]
    python infer.py expressions=take.csv audio=take.mov voice=voice.json

The fit (``motion.voice.fit``) finds ``slope`` (mm per semitone), ``rise`` and ``fall`` (s) so that the
voice term explains what the expression model (``checkpoint``, by default the shipped one, the model
``infer.py`` adds the voice term to) leaves of each pair's tau; ``voice.*`` are the fixed parameters (and
the tracker range).  ``out`` gets the fitted parameters and the fit's report as JSON.  Bad input: one line
``error: ...`` naming the file, exit status 2, nothing written.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from omegaconf import DictConfig

from base.cli import register_config, to_dataclass
from base.errors import InputError
from data.pairs import load_pairs
from models.checkpoint import load_model
from models.larynx import predict_tau
from models.pretrained import chosen_checkpoint
from motion.voice.config import VoiceConfig, save_voice
from motion.voice.fit import VoiceFit, fit_voice


@dataclass
class VoiceCli:
    """The settings of ``python -m motion.voice`` (``configs/voice.yaml`` composes it)."""

    mode: str = "fit"                  # fit
    pairs: str | None = None           # a folder of pair files with f0 (python -m data.pairs ... audio=)
    out: str | None = None             # voice.json to write
    checkpoint: str = "default"        # the expression model whose prediction is subtracted: default | none | file
    subject: str | None = None         # its subject style (null: the average style)
    voice: VoiceConfig = field(default_factory=VoiceConfig)  # fixed parameters (knee, high_ratio, hold, range)

    def __post_init__(self) -> None:
        if self.mode != "fit":
            raise ValueError(f"mode={self.mode}: expected 'fit'")


register_config("voice_schema", VoiceCli)


def expression_residuals(pairs, checkpoint: str, subject: str | None) -> tuple[list, list[np.ndarray], str | None]:
    """(pairs, tau minus the expression model's tau per pair, the model's label); the pairs resampled to the
    model's rate when there is a model."""
    path, label = chosen_checkpoint(checkpoint, "larynx_transformer", "checkpoint", "larynx")
    if path is None:
        return pairs, [p.tau for p in pairs], None
    model = load_model(path, task="larynx_transformer")[0]
    pairs = [p.resampled(model.fps) for p in pairs]
    return pairs, [p.tau - predict_tau(model, p.psi, subject) for p in pairs], label


def run(cfg: DictConfig) -> VoiceFit:
    """``mode=fit``: read ``pairs``, fit, write ``out``, print the report."""
    settings: VoiceCli = to_dataclass(cfg, where="voice (configs/voice.yaml)")
    for key, example in (("pairs", "pairs/"), ("out", "voice.json")):
        if not getattr(settings, key):
            raise InputError(f"mode=fit needs {key}={example}")
    pairs = load_pairs(settings.pairs)
    lacking = [p.name for p in pairs if p.f0 is None]
    if lacking:
        raise InputError(f"{settings.pairs}: {len(lacking)} pair file(s) without f0 ({', '.join(lacking[:3])}); "
                         f"expected pairs made with python -m data.pairs ... audio=<the take's sound>")
    pairs, residuals, model = expression_residuals(pairs, settings.checkpoint, settings.subject)
    fit = fit_voice(pairs, residuals, settings.voice)
    report = {**fit.report(), "pairs_folder": str(settings.pairs), "expression_model": model or "none"}
    save_voice(settings.out, fit.voice, report)
    v = fit.voice
    print(f"{settings.out}: slope {v.slope:.3f} mm/semitone ({12 * v.slope:.1f} mm/octave), rise {v.rise:.3f} s, "
          f"fall {v.fall:.3f} s; R^2 {fit.r2:.3f} over {fit.pairs} pair(s), {fit.frames} frames "
          f"({100 * fit.voiced:.0f}% voiced)")
    return fit
