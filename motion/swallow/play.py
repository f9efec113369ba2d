"""Swallow playback: insert a swallow template into tau tracks, scaled and blended."""
from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from motion.swallow.register import SwallowTemplate


@dataclass
class PlaybackConfig:
    """How an inserted swallow blends into a track (``configs/swallow.yaml: playback``,
    ``configs/infer.yaml: swallow_playback``)."""

    fade_seconds: float = 0.2             # (> 0) raised-cosine cross-fade at both ends of an inserted swallow
    rest_window_seconds: float = 0.5      # the track's rest level is the median over this window before/after
    blend: str = "replace"                # replace: cross-fade to rest + template; add: add the template

    def __post_init__(self) -> None:
        if self.blend not in ("replace", "add"):
            raise ValueError(f"PlaybackConfig.blend must be 'replace' or 'add', got '{self.blend}'")
        if not self.fade_seconds > 0:
            raise ValueError(f"PlaybackConfig.fade_seconds must be positive, got {self.fade_seconds}")
        if not self.rest_window_seconds >= 0:
            raise ValueError(f"PlaybackConfig.rest_window_seconds must be >= 0, got {self.rest_window_seconds}")


def _per_insert(name: str, value, count: int) -> np.ndarray:
    value = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if value.ndim != 1 or len(value) not in (1, count):
        raise ValueError(f"insert_swallows: {name} has {value.size} values for {count} inserts; "
                         f"give one value or one per insert")
    return np.broadcast_to(value, (count,))


def insert_swallows(tau: np.ndarray, time: np.ndarray, template: SwallowTemplate, at: Sequence[float] | float,
                    duration_scale: float | Sequence[float] = 1.0, amplitude_scale: float | Sequence[float] = 1.0,
                    config: PlaybackConfig | None = None) -> np.ndarray:
    """Insert the swallow template into tau tracks at given onset times.

    Insert j plays the template stretched by ``duration_scale[j]`` in time and ``amplitude_scale[j]``
    in height, its onset (template time 0) at ``at[j]`` seconds.  A weight w rises from 0 to 1 over
    ``fade_seconds`` (raised cosine) at the start of the scaled template span and falls back at its
    end (shortened to the template's rest padding before its onset, if shorter).  ``blend='replace'``:
    out = (1-w) tau + w (rest + template), where rest goes linearly from the track's median over
    ``rest_window_seconds`` before the insert to that after it (the track's own motion there is
    cross-faded away); ``blend='add'``: out = tau + w template.  Inserts are applied in order.

    Args:
        tau: [..., T] tau tracks (tau units), e.g. [T] from the tracker or a file, [B,T] from the
            larynx transformer.
        time: [T] seconds, shared by the tracks.
        template: the swallow (``read_template`` or ``build_template(...).template``).
        at: [J] onset times (s), or one number.
        duration_scale: one factor or [J], > 0.
        amplitude_scale: one factor or [J].
        config: fades and blending (defaults: :class:`PlaybackConfig`).

    Returns:
        [..., T] float64: the tracks with the swallows in.

    Raises:
        ValueError: tau and time disagree on T, a scale list does not match ``at``, a duration scale is
            not positive, or an insert lies entirely outside the track.
    """
    cfg = config or PlaybackConfig()
    out = np.array(tau, dtype=np.float64, copy=True)
    time = np.asarray(time, dtype=np.float64)
    if out.shape[-1] != len(time):
        raise ValueError(f"insert_swallows: tau {out.shape} and time {time.shape} disagree on T")
    at = np.atleast_1d(np.asarray(at, dtype=np.float64))
    durations = _per_insert("duration_scale", duration_scale, len(at))
    amplitudes = _per_insert("amplitude_scale", amplitude_scale, len(at))
    if (durations <= 0).any():
        raise ValueError(f"insert_swallows: duration_scale must be positive, got {durations}")
    for onset, stretch, gain in zip(at, durations, amplitudes):
        start = onset + stretch * template.time[0]
        stop = onset + stretch * template.time[-1]
        if stop <= time[0] or start >= time[-1]:
            raise ValueError(f"insert_swallows: a swallow at {onset:g} s spans [{start:.2f}, {stop:.2f}] s, "
                             f"outside the track [{time[0]:.2f}, {time[-1]:.2f}] s")
        curve = gain * template((time - onset) / stretch)
        # The fades lie in the template's rest padding before the onset (and as long after) when it is long enough.
        lead = -stretch * template.time[0]
        fade = min(cfg.fade_seconds, lead if lead > 0 else 0.5 * (stop - start))
        ramp_in = np.clip((time - start) / fade, 0.0, 1.0)
        ramp_out = np.clip((stop - time) / fade, 0.0, 1.0)
        weight = 0.5 - 0.5 * np.cos(np.pi * np.minimum(ramp_in, ramp_out))
        if cfg.blend == "add":
            out = out + weight * curve
            continue
        before = (time >= start - cfg.rest_window_seconds) & (time <= start)
        after = (time >= stop) & (time <= stop + cfg.rest_window_seconds)
        level_before = np.median(out[..., before], axis=-1) if before.any() else None
        level_after = np.median(out[..., after], axis=-1) if after.any() else None
        if level_before is None and level_after is None:
            level_before = level_after = np.median(out, axis=-1)
        level_before = level_after if level_before is None else level_before
        level_after = level_before if level_after is None else level_after
        progress = np.clip((time - start) / (stop - start), 0.0, 1.0)
        rest = np.asarray(level_before)[..., None] * (1 - progress) + np.asarray(level_after)[..., None] * progress
        out = (1 - weight) * out + weight * (rest + curve)
    return out
