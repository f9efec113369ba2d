"""Synthetic normal-map sequences of the neck with the ground-truth larynx position, to test the tracker.

A sequence is rendered from the rig (``scene.render``, default neck view, orthographic or perspective)
with a known generating process, deterministic from its seed:

- tau: ``data.synthetic_tau.random_tau_trajectory`` (rest, swallows,
  speech-like 2-6 Hz motion, slow drift), UV units, + = up the neck.
- head motion: a smooth random rotation per axis of the joints' ANATOMICAL
  frames (``models.rig``: x flexion, y axial rotation, z lateral bending; a
  sum of three sinusoids below ``head_motion_hz``), scaled so its largest
  excursion is ``head_motion_deg`` (each axis draws a peak in [0.5, 1] x
  that), spread evenly over the 8 cervical joints (each joint turns 1/8 of
  it, so the head turns by about the whole).  The rig is posed with
  ``rig.from_anatomical(theta)`` (its bone frames need not be anatomical:
  the real HACK rig's oc1 bone points into the face).
- expressions (optional, ``expressions=<recording>``): the face replays a
  real recording (``data.expressions.read_expressions``: Live Link Face,
  ARKit or HACK CSV, or a ``.npy`` [T,55] with ``expressions_fps``),
  resampled to ``fps``, from ``expression_start`` seconds (default: a
  seeded start within the recording; looped when the sequence is longer):
  the jaw, lips and chin move above the larynx as when the subject talks.
- eta: one larynx size per sequence, uniform in [``eta_min``, ``eta_max``].
- image degradation, in order: optional Gaussian blur (``blur_px`` sigma,
  pixels), per-pixel Gaussian noise of std ``noise`` on each normal component,
  renormalised; optional 8-bit quantisation of the RGB encoding.
  Background pixels stay 0.

Ground truth: ``larynx_px [T,2]`` = (col, row) of the projection of the
rig's larynx point (``scene.render.larynx_point``: the area-weighted centroid
of the posed surface where the larynx term exceeds 30 % of its maximum,
weighted by the excess), in the image convention of ``scene.render`` (pixel
centres at integers, rows down).  The tracker's rig kernel is centred on the
same point at rest, so its reported position estimates exactly this.
``slide_px [T,2]`` is the same point with the head still (theta 0, same tau,
eta and expressions): the larynx's slide alone, what a tracker that
compensates the head's motion estimates.

How well a position explains tau: :func:`tau_r2` (the R^2 of tau fitted
linearly from a rise in pixels); :meth:`NormalSequence.ceiling_r2` is that of
the true image position, the best a tracker of the image position can do.

CLI (hydra, ``configs/normal_sequences.yaml``, settings :class:`SequencesCli`)::

    python -m scene.normal_sequences out=frames/ frames=300 seed=0 [format=png8|png16|exr|npy] [noise=0.05]
        [expressions=take.csv] [head_motion_deg=15] [perspective=true] [rig=hack_rig.npz]

writes ``frame_00000.png ...`` (or ``normals.npy`` [T,H,W,3] float32 raw normals) and ``truth.csv``
(``frame,time,tau,x_px,y_px,slide_x_px,slide_y_px,eta,fps``, ``data.tau_track.write_tau_track``; x_px/y_px
and slide_*_px the ground truth above) into ``out``.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass

from base.cli import REQUIRED, register_config, to_dataclass
from base.files import fresh_output_folder
from models.rig import HeadNeckModel
from scene.normal_sequences.sequence import (
    SEQUENCE_FILES,
    SEQUENCE_FORMATS,
    NormalSequence,
    SequenceConfig,
    make_sequence,
    write_sequence,
)


@dataclass
class SequencesCli(SequenceConfig):
    """``python -m scene.normal_sequences``: the generator's settings (:class:`SequenceConfig`, flat) and
    where to write."""

    out: str = REQUIRED                   # folder for the frames and truth.csv
    format: str = "png8"                  # png8 | png16 | exr (float raw normals) | npy (one [T,H,W,3] float32 stack)
    seed: int = 0
    rig: str = "builtin"                  # or a rig file from python -m data.assets
    # torch threads: 2 are faster on a quiet machine (103 vs 83 frames/s), 1 when the cores are shared (48 vs 15)
    threads: int = 1

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.format not in SEQUENCE_FORMATS:
            raise ValueError(f"format={self.format}: expected {', '.join(SEQUENCE_FORMATS)}")


register_config("normal_sequences_schema", SequencesCli)


def run(cfg) -> NormalSequence:
    """The CLI's work for a composed ``configs/normal_sequences.yaml`` (tests call this in-process)."""
    settings = to_dataclass(cfg, where="configs/normal_sequences.yaml")
    fresh_output_folder(settings.out, SEQUENCE_FILES, "out")   # before rendering: fail fast on a used folder
    started = _time.perf_counter()
    sequence = make_sequence(HeadNeckModel.from_config(settings.rig), settings, int(settings.seed))
    rendered = _time.perf_counter() - started
    write_sequence(settings.out, sequence, settings.format)
    print(f"rendered {len(sequence)} frames of {settings.size}x{settings.size} in {rendered:.1f} s "
          f"({len(sequence) / rendered:.0f} frames/s); wrote {settings.format} frames and truth.csv to {settings.out}")
    return sequence
