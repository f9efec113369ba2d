"""Swallow files: templates (CSV ``time,tau,std``), the tau tracks they are built from, and plots."""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np

from base.errors import InputError
from base.files import write_csv
from base.plots import figure, save_figure
from base.tables import CsvTable
from base.timebase import check_increasing, estimate_fps
from data.tau_track import TauTrack, read_tau_track
from motion.swallow.register import SwallowTemplate, TemplateBuild, template_error

TEMPLATE_KIND = "a swallow template written by python -m motion.swallow (CSV time,tau,std; time 0 = onset)"


def write_template(path: str | Path, template: SwallowTemplate) -> None:
    """Write a template as CSV ``time,tau,std`` (time 0 = onset), atomically."""
    write_csv(path, {"time": template.time, "tau": template.tau, "std": template.std}, float_format="%.9g")


def read_template(path: str | Path) -> SwallowTemplate:
    """Read a template written by :func:`write_template`.

    Args:
        path: CSV ``time,tau,std``; time (s) increasing, from at or before 0 (the onset; the rest padding
            is negative time) to after it; std >= 0.

    Returns:
        :class:`SwallowTemplate` (time [S], tau [S], std [S], fps from the time stamps; landmark: the onset).

    Raises:
        InputError: naming the file (and column, line) for anything else, e.g. a tau track
            (``time,tau`` without ``std``).
    """
    path = Path(path)
    if path.suffix.lower() != ".csv":
        raise InputError(f"{path}: not {TEMPLATE_KIND}: got '{path.suffix}'")
    table = CsvTable(path)
    if not table.has("std"):
        raise InputError(f"{path}: not {TEMPLATE_KIND}: no column 'std' (columns: {', '.join(table.header)})")
    if len(table) < 3:
        raise InputError(f"{path}: {len(table)} rows, a swallow template needs at least 3")
    time, tau, std = table.numeric("time"), table.numeric("tau"), table.numeric("std")
    check_increasing(time, table, "time")
    if not time[0] <= 0.0 < time[-1]:
        raise InputError(f"{path}: not {TEMPLATE_KIND}: column 'time' runs {time[0]:g} to {time[-1]:g} s, expected "
                         f"it to start at or before 0 (the onset) and end after it")
    if (std < 0).any():
        i = int(np.argmax(std < 0))
        raise InputError(f"{path}: column 'std', line {table.lines[i]}: negative ({std[i]:g}), expected >= 0")
    return SwallowTemplate(time, tau, std, estimate_fps(time), np.array([0.0]), ("onset",))


def read_tracks(paths: Sequence[str | Path], fps: float | None = None,
                min_confidence: float | None = None) -> list[TauTrack]:
    """Tau tracks from CSV or .npy files (``data.tau_track.read_tau_track``).

    ``fps``: the frame rate of files that carry none (.npy, a CSV with ``frame`` but no ``time``/``fps``);
    ``min_confidence``: tracker rows below it are dropped (files without a ``confidence`` column are read
    whole).  Errors name the file and the config key (``fps``).
    """
    return [read_tau_track(p, fps=fps, min_confidence=min_confidence, fps_key="fps") for p in paths]


def plot_template(path: str | Path, build: TemplateBuild) -> None:
    """Aligned swallows, the template +- std and the naive unaligned mean, saved atomically."""
    t = build.template
    fig, ax = figure(figsize=(9, 5))
    for k, curve in enumerate(build.aligned):
        ax.plot(t.time, curve, color="0.6", lw=0.8, label="aligned swallows" if k == 0 else None)
    ax.fill_between(t.time, t.tau - t.std, t.tau + t.std, color="C0", alpha=0.25, label="template ± std")
    ax.plot(t.time, t.tau, color="C0", lw=2.2, label=f"template ({len(build.events)} swallows)")
    if len(build.naive_time) > 1:
        _, shift, _ = template_error(build.naive_time, build.naive_tau, t.time, t.tau,
                                     max_shift=max(2.0, float(build.naive_time[-1])), scale_range=(1.0, 1.0))
        ax.plot(build.naive_time + shift, build.naive_tau, color="C3", ls="--", lw=1.6,
                label=f"naive unaligned mean (clip starts aligned, shifted {shift:+.2f} s)")
    bottom = ax.get_ylim()[0]
    for name, x in zip(t.landmark_names, t.landmarks):
        crossing = name[:4] in ("rise", "fall") and name[4:].isdigit()
        if not crossing or name.endswith("50"):  # the other level crossings would crowd the plot
            ax.axvline(x, color="0.3", ls=":", lw=0.8)
            ax.text(x, bottom, f" {name}", rotation=90, va="bottom", ha="right", fontsize=8)
    ax.set_xlim(t.time[0], t.time[-1])
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel("time from onset (s)")
    ax.set_ylabel("tau above rest (UV units; 0.03 ≈ 1 cm)")
    ax.set_title("Swallow template: landmark-registered mean")
    ax.legend(loc="upper right", fontsize=8)
    save_figure(fig, path, dpi=110)


def plot_playback(path: str | Path, track: TauTrack, out: np.ndarray, at: Sequence[float]) -> None:
    """The input track, the track with the swallows and their onsets, saved atomically."""
    fig, ax = figure(figsize=(10, 4))
    ax.plot(track.time, track.tau, color="0.5", lw=1, label="input track")
    ax.plot(track.time, out, color="C0", lw=1.5, label="with swallows")
    for x in at:
        ax.axvline(x, color="C3", ls=":", lw=0.8)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("tau (UV units)")
    ax.legend(loc="upper right", fontsize=8)
    save_figure(fig, path, dpi=110)
