"""``python -m motion.swallow``: build a swallow template from tau tracks, or play one into a track.

    python -m motion.swallow inputs=[a.csv,b.csv] out=template.csv [plot=template.png]
    python -m motion.swallow mode=play track=in.csv template=template.csv at=[2.0,7.5] out=out.csv \\
        [duration_scale=1.2] [amplitude_scale=0.8] [plot=play.png]

Inputs are tau tracks (``data.tau_track.read_tau_track``: CSV with ``tau`` and ``time`` or ``frame``
[+ ``fps``], or ``.npy``); ``fps=...`` is the frame rate of files that carry none (``.npy``, a CSV
with ``frame`` but no ``time`` or ``fps`` column).  Tracker CSVs (``python -m motion.track``) lose
the rows below ``min_confidence`` (lost and rejected frames; the track is resampled over the gap).
``inputs`` and ``at`` take one value or a list (``inputs=a.csv``, ``at=2.0``).  Thresholds:
``detection.*`` (:class:`motion.swallow.detect.DetectionConfig`), ``registration.*``
(:class:`motion.swallow.register.RegistrationConfig`), ``playback.*``
(:class:`motion.swallow.play.PlaybackConfig`).  Bad input: one line ``error: ...`` naming the file,
exit status 2.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Any

from omegaconf import DictConfig

from base.cli import as_list, register_config, to_dataclass
from base.errors import InputError
from data.tau_track import TauTrack, write_tau_track
from motion.swallow.detect import uniform_track
from motion.swallow.events import DetectionConfig
from motion.swallow.files import plot_playback, plot_template, read_template, read_tracks, write_template
from motion.swallow.play import PlaybackConfig, insert_swallows
from motion.swallow.register import RegistrationConfig, TemplateBuild, build_template


@dataclass
class SwallowCli:
    """The settings of ``python -m motion.swallow`` (schema and defaults; ``configs/swallow.yaml`` composes it)."""

    mode: str = "template"                # template | play
    fps: float | None = None              # frame rate of tracks that carry none: .npy, CSV without a time/fps column
    min_confidence: float | None = 0.3    # drop tracker frames below it (interpolated over); null keeps all
    out: str | None = None                # template.csv (mode=template) or the output track .csv/.npy (mode=play)
    plot: str | None = None               # optional .png
    inputs: Any = field(default_factory=list)  # mode=template: tau tracks (CSV or .npy); one or a list
    track: str | None = None              # mode=play: the tau track to insert into
    template: str | None = None           # mode=play: template CSV (time,tau,std; time 0 = onset)
    at: Any = field(default_factory=list)  # mode=play: onset times (s); one or a list
    duration_scale: Any = 1.0             # one value or one per insert
    amplitude_scale: Any = 1.0            # one value or one per insert
    detection: DetectionConfig = field(default_factory=DetectionConfig)
    registration: RegistrationConfig = field(default_factory=RegistrationConfig)
    playback: PlaybackConfig = field(default_factory=PlaybackConfig)

    def __post_init__(self) -> None:
        if self.mode not in ("template", "play"):
            raise ValueError(f"mode={self.mode}: expected 'template' or 'play'")


register_config("swallow_schema", SwallowCli)


def _section(cfg: DictConfig, key: str):
    return to_dataclass(cfg[key], where=f"{key} (configs/swallow.yaml)")


def run_template(cfg: DictConfig) -> TemplateBuild:
    """``mode=template``: read ``inputs``, build the template, write ``out`` (and ``plot``), print the report."""
    inputs = as_list(cfg.inputs)
    if not inputs:
        raise InputError("inputs=[a.csv,b.csv,...] is required (tau tracks: CSV or .npy)")
    if not cfg.out:
        raise InputError("out=template.csv is required")
    started = _time.perf_counter()
    detection, registration = _section(cfg, "detection"), _section(cfg, "registration")
    tracks = read_tracks(inputs, cfg.fps, cfg.min_confidence)
    build = build_template(tracks, detection, registration)
    write_template(cfg.out, build.template)
    if cfg.plot:
        plot_template(cfg.plot, build)
    print(build.report())
    print(f"wrote {cfg.out}" + (f" and {cfg.plot}" if cfg.plot else "") + f" in {_time.perf_counter() - started:.1f} s")
    return build


def run_play(cfg: DictConfig) -> TauTrack:
    """``mode=play``: insert ``template`` into ``track`` at ``at`` seconds, write ``out`` (and ``plot``)."""
    for key, example in (("track", "in.csv"), ("template", "template.csv"), ("out", "out.csv")):
        if not cfg.get(key):
            raise InputError(f"mode=play needs {key}={example}")
    at = as_list(cfg.at)
    if not at:
        raise InputError("mode=play needs at=[t1,t2,...] (onset times in seconds)")
    try:
        at = [float(a) for a in at]
    except (TypeError, ValueError):
        raise InputError(f"at={at}: expected onset times in seconds (a number or a list of numbers)") from None
    playback = _section(cfg, "playback")
    (read,) = read_tracks([cfg.track], cfg.fps, cfg.min_confidence)
    track = uniform_track(read)  # over dropped tracker frames: the output is a complete frame,time,tau track
    template = read_template(cfg.template)
    durations, amplitudes = as_list(cfg.duration_scale), as_list(cfg.amplitude_scale)
    try:
        out = insert_swallows(track.tau, track.time, template, at, durations, amplitudes, playback)
    except ValueError as e:
        raise InputError(f"{cfg.track}: {e}") from None
    result = TauTrack(out, track.time, track.fps, str(cfg.out))
    write_tau_track(cfg.out, result)
    if cfg.plot:
        plot_playback(cfg.plot, track, out, at)
    resampled = "" if track is read else (f" ({len(read)} rows resampled to {len(track)} uniform frames at "
                                          f"{track.fps:g} fps)")
    print(f"inserted {len(at)} swallow(s) (peak {template.peak_height:.4f} tau x amplitude {cfg.amplitude_scale}, "
          f"duration x {cfg.duration_scale}) into {cfg.track}{resampled} at {', '.join(f'{a:g}' for a in at)} s; "
          f"wrote {cfg.out}")
    return result


def run(cfg: DictConfig) -> TemplateBuild | TauTrack:
    """The CLI's work for a composed ``configs/swallow.yaml`` (tests call this in-process).

    Every settings section is validated first, whichever mode uses it."""
    for key in ("detection", "registration", "playback"):
        _section(cfg, key)
    if cfg.mode == "template":
        return run_template(cfg)
    if cfg.mode == "play":
        return run_play(cfg)
    raise InputError(f"mode={cfg.mode}: expected 'template' or 'play'")
