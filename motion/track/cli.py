"""``python -m motion.track``: track the larynx through normal maps and write the track (CSV and plot).

    python -m motion.track input=frames/ out=track.csv [init_x=128 init_y=130] [cm_per_px=0.08]
        [kernel=rig|frame|kernel.npy] [rig=hack_rig.npz] [px_per_tau=auto|<number>|null] [fps=30]
        [compensate=true]

The capture's pixel scale at the neck (``cm_per_px``) sizes the kernel (70 px at 0.08 cm/px, at most 5/8 of
the frame's short side, unless ``kernel_size`` is given), the tracker's pixel settings
(``TrackerConfig.at_scale``), the window's calibration, the neck model and ``px_per_tau``.
Without ``cm_per_px=`` it is estimated from the first 90 frames (``motion.track.scale``: the rig's neck
matched over the part of it the frames show, at scales 0.005-0.64 cm/px, views of 4.8 to 100 cm; see
``benchmarks/README.md`` for its errors from the whole head to 6.4 cm of neck) and
printed (``scale: 0.0812 cm/px, estimated ...``); a given ``cm_per_px`` that differs from the frames'
by more than 15 % is used but warned about (one ``warning:`` line on stderr).

Settings: :class:`TrackCli` (``configs/track.yaml`` holds what differs from its defaults).  Writes
``frame,time,x_px,y_px,tau_px,tau,confidence,tau_px_raw,neck_dx_px,neck_dy_px``:

- (x_px, y_px): the larynx point's position (col, row; rows go down) in the image, the kernel's centre
  (for the rig kernel the rig's ``scene.render.larynx_point``).
- tau_px_raw = y_rest - y_px (positive = up), the rest row being the position in frame ``rest_frame``.
- neck_dx_px, neck_dy_px: the neck's own displacement at the larynx relative to the first frame
  (``motion.track.neck``; NaN when it is not estimated: ``tracker.neck.follow=false`` without
  ``compensate``).
- tau_px: with ``compensate=true`` the larynx's rise relative to the neck,
  tau_px_raw + (neck_dy_px - neck_dy_px[rest_frame]); else tau_px_raw.
- tau = tau_px / px_per_tau: ``px_per_tau`` (pixels of upward image motion per tau unit) from the rig
  for the default neck view at the capture's ``cm_per_px`` (``auto``, kernel=rig only), given, or
  absent (``null``: the column is NaN).
- confidence: the match's weighted normalised correlation, 0 where the frame was rejected (held).
"""
from __future__ import annotations

import sys
import time as _time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from base.cli import REQUIRED, register_config, to_dataclass
from base.errors import InputError
from base.files import write_csv
from base.plots import figure, save_figure
from models.rig import HeadNeckModel
from motion.track.calibration import calibrate_window, rig_px_per_tau
from motion.track.config import TrackerConfig
from motion.track.kernel import (
    LarynxKernel,
    kernel_from_file,
    kernel_from_frame,
    kernel_size_at,
    rescale_kernel,
    rig_kernel,
)
from motion.track.match import Track, track_sequence
from motion.track.neck import NeckModel
from motion.track.scale import check_scale, estimate_scale, sample_frames
from motion.track.sources import FLOAT_ENCODINGS, open_source
from scene.render import neck_camera

CSV_COLUMNS = ("frame", "time", "x_px", "y_px", "tau_px", "tau", "confidence", "tau_px_raw", "neck_dx_px",
               "neck_dy_px")


@dataclass
class TrackCli:
    """``python -m motion.track``: what to track, with which kernel, and what to write."""

    input: str = REQUIRED           # folder of PNG (8/16-bit) / TIFF / EXR images, a video, or a .npy stack [T,H,W,3]
    out: str = REQUIRED             # track.csv
    plot: str | None = "auto"       # auto = beside out (.png); a path; or null for none
    fps: float | None = None        # frame rate; default: the video's own, 30 for image folders and .npy stacks
    float_encoding: str = "auto"    # float data (EXR, float .npy): raw normals in [-1,1], encoded (n+1)/2, or auto
    # rig (rendered from the rig, its window calibrated on it) | frame (cut from the first frame at
    # init_x/init_y) | a kernel file (.npy [h,w,3], .png, .tif, .exr)
    kernel: str = "rig"
    rig: str = "builtin"            # the rig (kernel=rig, px_per_tau=auto, the neck model): builtin or a rig file
    cm_per_px: float | None = None  # the capture's pixel scale at the neck; without: estimated from the frames
    kernel_cm_per_px: float | None = None  # a kernel file's own scale, to rescale it to cm_per_px
    kernel_size: int | None = None  # pixels (kernel=rig and kernel=frame); default 70 at 0.08 cm/px (5.6 cm), scaled
    init_x: float | None = None     # larynx position in the first frame (column); without: the whole frame is searched
    init_y: float | None = None     # (row, rows go down)
    px_per_tau: str | None = "auto"  # auto (from the rig, kernel=rig only) | a number | null (no tau)
    rest_frame: int = 0             # tau_px = y(rest_frame) - y
    compensate: bool = False        # tau_px relative to the neck's own motion (the raw rise stays in tau_px_raw)
    threads: int = 2
    progress: bool = True
    tracker: TrackerConfig = field(default_factory=TrackerConfig)

    def __post_init__(self) -> None:
        if self.float_encoding not in FLOAT_ENCODINGS:
            raise ValueError(f"float_encoding={self.float_encoding}: expected auto, raw or encoded")
        if self.cm_per_px is not None and not self.cm_per_px > 0:
            raise ValueError(f"cm_per_px={self.cm_per_px}: expected a positive pixel scale")
        if self.kernel_size is not None and self.kernel_size < 5:
            raise ValueError(f"kernel_size={self.kernel_size}: expected at least 5 pixels")


register_config("track_schema", TrackCli)


def calibration(settings: TrackCli) -> float | None:
    """``px_per_tau`` as a number, or None for auto (resolved by the caller) and null."""
    if settings.px_per_tau in (None, "auto"):
        return None
    try:
        value = float(settings.px_per_tau)
    except ValueError:
        raise InputError(f"px_per_tau={settings.px_per_tau}: expected auto, a number or null") from None
    if not np.isfinite(value) or value == 0:
        raise InputError(f"px_per_tau={settings.px_per_tau}: expected a non-zero number")
    return value


def capture_scale(settings: TrackCli, source, rig) -> float:
    """The capture's cm_per_px: the given one (warned about on stderr when the frames disagree with it) or
    the frames' estimate (``motion.track.scale``); prints one line naming it."""
    frames = sample_frames(normals for _, _, normals in source.frames())
    if settings.cm_per_px is not None:
        warning = check_scale(frames, rig, float(settings.cm_per_px), settings.tracker.bandpass)
        if warning:
            print(warning, file=sys.stderr)
        print(f"scale: {settings.cm_per_px:g} cm/px (given)")
        return float(settings.cm_per_px)
    estimate = estimate_scale(frames, rig, settings.tracker.bandpass)
    print(f"scale: {estimate.cm_per_px:.4g} cm/px, estimated from {estimate.frames} frames (peak correlation "
          f"{estimate.score:.2f} with the rig's neck); give cm_per_px= to set it")
    return estimate.cm_per_px


def build_kernel(settings: TrackCli, first_frame: np.ndarray, first_label: str, rig_loader,
                 config: TrackerConfig, cm_per_px: float) -> LarynxKernel:
    """The kernel the settings ask for (``kernel=rig|frame|<file>``), at the capture's scale ``cm_per_px``."""
    size = int(settings.kernel_size or kernel_size_at(cm_per_px, first_frame.shape))
    if settings.kernel == "rig":
        rig = rig_loader()
        return calibrate_window(rig_kernel(rig, cm_per_px, size), rig, config)
    if settings.kernel == "frame":
        if settings.init_x is None or settings.init_y is None:
            raise InputError("kernel=frame cuts the kernel from the first frame: give init_x=... init_y=... "
                             "(the larynx's pixel position in it)")
        return kernel_from_frame(first_frame, float(settings.init_x), float(settings.init_y), size, first_label,
                                 cm_per_px)
    kernel = kernel_from_file(settings.kernel, settings.kernel_cm_per_px, settings.float_encoding)
    return rescale_kernel(kernel, cm_per_px)


def track_columns(track: Track, fps: float, rest_frame: int = 0, px_per_tau: float | None = None,
                  compensate: bool = False) -> dict:
    """The CSV columns (``CSV_COLUMNS``, see the module doc) of a track at ``fps``."""
    if not 0 <= rest_frame < len(track):
        raise InputError(f"rest_frame={rest_frame}: expected a frame index in [0, {len(track) - 1}]")
    if not np.isfinite(track.y[rest_frame]):
        raise InputError(f"rest_frame={rest_frame}: the larynx was not found in that frame; choose another")
    raw = track.y[rest_frame] - track.y
    relative = raw + (track.neck[:, 1] - track.neck[rest_frame, 1])
    if compensate and not np.isfinite(track.neck[rest_frame]).all():
        raise InputError(f"compensate=true: the neck's motion was not measured in rest_frame={rest_frame}")
    tau_px = relative if compensate else raw
    tau = tau_px / px_per_tau if px_per_tau else np.full(len(track), np.nan)
    frames = np.arange(len(track))
    return {"frame": frames, "time": frames / fps, "x_px": track.x, "y_px": track.y, "tau_px": tau_px, "tau": tau,
            "confidence": track.confidence, "tau_px_raw": raw, "neck_dx_px": track.neck[:, 0],
            "neck_dy_px": track.neck[:, 1]}


def plot_track(path: str | Path, columns: dict, accepted: np.ndarray, px_per_tau: float | None = None,
               title: str = "", compensated: bool = False) -> None:
    """tau_px over time (and tau, with a calibration ``px_per_tau``), the raw rise beside the compensated
    one, the rejected frames (``accepted`` [T] False) marked, and the confidence, as a PNG (atomic).
    ``columns``: :func:`track_columns`."""
    time = columns["time"]
    fig, (top, bottom) = figure(nrows=2, ncols=1, figsize=(9, 5), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    if compensated:
        top.plot(time, columns["tau_px_raw"], color="0.6", lw=1.0, label="raw image rise")
    top.plot(time, columns["tau_px"], color="tab:blue", lw=1.2,
             label="rise relative to the neck" if compensated else "rise")
    top.set_ylabel("larynx rise tau_px (px, + = up)")
    if px_per_tau:
        right = top.secondary_yaxis("right", functions=(lambda p: p / px_per_tau, lambda t: t * px_per_tau))
        right.set_ylabel("tau (UV units)")
    rejected = ~np.asarray(accepted, dtype=bool)
    if rejected.any():
        top.plot(time[rejected], columns["tau_px"][rejected], "x", color="tab:red", ms=4, label="rejected (held)")
    top.legend(loc="upper right")
    top.set_title(title)
    top.grid(alpha=0.3)
    bottom.plot(time, columns["confidence"], color="tab:green", lw=1.0)
    bottom.set_ylim(0, 1.02)
    bottom.set_ylabel("confidence")
    bottom.set_xlabel("time (s)")
    bottom.grid(alpha=0.3)
    save_figure(fig, path, dpi=100)


def run(cfg) -> dict:
    """The CLI's work for a composed ``configs/track.yaml`` (tests call this in-process); returns the columns."""
    settings: TrackCli = to_dataclass(cfg, where="configs/track.yaml")
    cv2.setNumThreads(int(settings.threads))  # torch's are set by base.cli.run_cli
    started = _time.perf_counter()
    source = open_source(settings.input, settings.fps, settings.float_encoding)
    px_per_tau = calibration(settings)
    rig_cache: list = []

    def rig_loader() -> HeadNeckModel:
        if not rig_cache:
            rig_cache.append(HeadNeckModel.from_config(settings.rig))
        return rig_cache[0]

    frames = source.frames()
    head = next(frames, None)
    if head is None:
        raise InputError(f"{settings.input}: no frames; expected at least one normal map")
    _, first_label, first = head
    cm_per_px = capture_scale(settings, source, rig_loader())
    config = settings.tracker.at_scale(cm_per_px)
    kernel = build_kernel(settings, first, first_label, rig_loader, config, cm_per_px)
    h, w = first.shape[:2]
    if kernel.size[0] > w or kernel.size[1] > h:
        raise InputError(f"{first_label}: the {kernel.size[0]}x{kernel.size[1]} kernel is larger than the "
                         f"{w}x{h} frames at {cm_per_px:.4g} cm/px; check cm_per_px= (the capture's scale) or "
                         f"give a smaller kernel_size")
    neck = None
    if settings.compensate or config.neck.follow:
        neck = NeckModel.from_rig(rig_loader(), neck_camera(rig_loader(), cm_per_px=cm_per_px), config.neck)
    init = None
    if settings.init_x is not None and settings.init_y is not None:
        init = (float(settings.init_x), float(settings.init_y))

    def all_frames():
        yield first
        for _, _, normals in frames:
            yield normals

    track = track_sequence(all_frames(), kernel, config, init, neck, progress=settings.progress, total=source.count)
    if settings.px_per_tau == "auto" and settings.kernel == "rig":
        px_per_tau = rig_px_per_tau(rig_loader(), cm_per_px)
    columns = track_columns(track, source.fps, settings.rest_frame, px_per_tau, settings.compensate)
    write_csv(settings.out, columns, float_format="%.9g")  # time of an hour-long take to 1e-5 s
    plot = settings.plot if settings.plot != "auto" else str(Path(settings.out).with_suffix(".png"))
    if plot:
        plot_track(plot, columns, track.accepted, px_per_tau, f"{Path(settings.input).name}: kernel {kernel.source}",
                   settings.compensate)
    elapsed = _time.perf_counter() - started
    rejected = int((~track.accepted).sum())
    scale = f"{px_per_tau:.1f} px per tau unit" if px_per_tau else "no calibration (tau column NaN)"
    print(f"tracked {len(track)} frames at {source.fps:g} fps in {elapsed:.1f} s; {rejected} rejected; "
          f"median confidence {np.median(track.confidence):.3f}; {scale}"
          + ("; tau_px relative to the neck" if settings.compensate else "") + f"; wrote {settings.out}"
          + (f" and {plot}" if plot else ""))
    return columns
