"""Expression/larynx pairs: the captured training data of the expression -> larynx transformer.

A *pair file* is an ``.npz`` holding one recording:
- ``psi`` [T,55]: expression weights in ``data.expressions.EXPRESSION_NAMES`` order;
- ``tau`` [T]: larynx slide in UV units of the larynx map, + = up the neck (``data.tau_track``);
- ``fps``: frames per second of both (a scalar);
- optional ``subject`` (a string naming the person), ``take`` (a string naming the recording the
  file was cut from), ``eta`` (larynx size, scalar), ``time`` [T] (seconds on the expression
  recording's clock, informative only) and ``f0`` [T] (the voice's F0 in Hz, 0 = unvoiced).

A *pairs folder* holds many such files; :func:`split_by_take` splits it into training and validation
**by take**, so clips cut from one recording are never on both sides.  A file without ``take`` belongs
to the take its name gives without a trailing clip number (:func:`take_from_name`: ``anna_take2_clip07``
and ``anna_take2_08`` are take ``anna_take2``; ``take3`` is ``take3``).

Capture workflow: the larynx tracker writes a tau track (CSV ``frame,time,x_px,y_px,tau_px,tau,
confidence``) and the face capture an expression recording (any format ``read_expressions``
reads); ``python -m data.pairs track=track.csv expressions=take.csv out=pair.npz`` aligns them by
time on their overlap, resampled to one rate::

    python -m data.pairs track=track.csv expressions=take.csv out=pairs/take1.npz \\
        [fps=30] [offset=0.25] [subject=anna] [min_confidence=0.3] [track_fps=..] [expressions_fps=..] \\
        [timecode_fps=..]

``offset`` (seconds) is added to the track's time (a tracker that started 0.25 s after the face
capture needs ``offset=0.25``); ``fps`` is the pair's (output) rate, by default the expression
recording's.  The inputs' own rates, where the files carry none, are ``track_fps`` (a ``.npy`` track or
a CSV without ``time``/``fps`` columns), ``expressions_fps`` (header-less or ``.npy`` expressions) and
``timecode_fps`` (a Live Link Face timecode too short to tell its rate).

``audio=take.wav|take.mov`` adds the take's voice F0 per frame (``f0``, Hz, 0 = unvoiced; ``data.audio``),
the audio starting with the expression recording: pairs for ``python -m motion.voice mode=fit``.
"""
from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from data.audio import read_audio
from data.expressions import read_expressions
from data.pairs.align import align_pair, f0_on_pair
from data.pairs.files import LarynxSequence, save_pair
from data.tau_track import read_tau_track


def run(cfg: DictConfig) -> LarynxSequence:
    """``python -m data.pairs``: align, write and report."""
    track = read_tau_track(cfg.track, fps=cfg.track_fps, min_confidence=cfg.min_confidence, fps_key="track_fps")
    expressions = read_expressions(cfg.expressions, fps=cfg.expressions_fps, timecode_fps=cfg.timecode_fps,
                                   fps_key="expressions_fps")
    pair, time = align_pair(track, expressions, cfg.fps, float(cfg.offset),
                            None if cfg.subject is None else str(cfg.subject), Path(cfg.out).stem)
    if cfg.get("audio"):
        pair.f0 = f0_on_pair(read_audio(cfg.audio), expressions, time)
    save_pair(cfg.out, pair, time)
    print(f"{cfg.out}: {len(pair)} frames at {pair.fps:g} fps ({time[0]:.3f}-{time[-1]:.3f} s of {cfg.expressions})")
    return pair
