"""Larynx tracker and normal-map renderer: speed, and accuracy on synthetic sequences per condition.

    python benchmarks/bench_tracker.py [--rig /tmp/hack_rig.npz] [--threads 1] [--frames 240] [--seeds 1]
        [--sections speed,slide,conditions,ablations,scale,framing] [--sizes 256,512] [--px-per-cm 8,12,...]

Sequences (``scene.normal_sequences``): 256x256 at 0.08 cm/px, 30 fps, noise 0.05, 8-bit quantised, swallows
(40 per minute), speech-like tau motion; per condition head motion (degrees per anatomical axis), the face
replaying a real recording (the Live Link Face samples in ``../shared/samples/livelinkface``, the HACK
release's ``bsw_list.npy`` at 30 fps; conditions whose recording is absent are skipped), perspective, blur.

Figures:
- speed: renderer frames/s (batches of 32 posed frames, the rig's forward pass included and not); tracker
  frames/s on decoded 256x256 frames without and with the neck's motion (compensation included; the
  target is >= 300), the whole path from 8-bit RGB, and the raw-correlation baseline.
- slide: noise-free renders, head still, tau -0.03..0.06 in 13 steps: the tracked rise over the larynx
  point's (slope of a line fit) and the error.
- conditions: per condition and seed, the R^2 of tau fitted linearly from the rise in pixels: of the true
  image position of the larynx point (the ceiling of any tracker of the image position), of the tracker's
  ``tau_px`` without compensation (raw) and with it (relative to the neck), of the tracker as it was
  before issue 16 (window centred on the kernel, low-pass 3 px, no neck), and of the baseline (integer
  arg-max of the raw correlation over the whole frame); the median error of the raw position (px).
- ablations (on the talking-and-moving conditions): without the window's calibration, low-pass 3 px,
  without the neck following the band, without the jaw's patch.
- scale (not among the default sections): talking-and-moving sequences (``SCALE_CONDITIONS``) rendered at
  0.5, 1 and 2 times 0.08 cm/px, the same view (512, 256 and 128 px square); per scale the R^2 (raw and
  compensated) of the tracker set up as ``python -m motion.track`` sets it up (kernel, window calibration,
  tracker settings and neck model at the scale) given the true scale and given the scale estimated from the
  frames (``motion.track.scale.estimate_scale``, the first 90 frames), the estimate, its error and its time.
- framing (not among the default sections): one talking-and-moving sequence (``FRAMING_CONDITION``, seed 0)
  rendered at 8, 12, 16, 22, 30 and 40 px/cm (``FRAMING_PX_PER_CM``) on 256x256 and 512x512 frames centred on
  the rest larynx point: from the whole head (64 cm across) down to 6.4 cm of neck filling the frame.  Per
  framing the R^2 (raw / compensated) given the true scale and given the estimate, the estimate's error and
  time; on 512x512 frames also the whole ``python -m motion.track`` run without ``cm_per_px=`` (its own
  estimate included, 8-bit frames read from a file) and its time.  A refused estimate prints the error.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from timing import frames_per_second  # noqa: E402
from tracker_baseline import raw_correlation_argmax  # noqa: E402

from base.errors import InputError  # noqa: E402
from data.normals import encode_normals, stored_to_unit  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402
from motion.track import (  # noqa: E402
    BandpassConfig,
    NeckModel,
    TrackerConfig,
    calibrate_window,
    check_normal_map,
    decode_frame,
    rig_kernel,
    track_sequence,
)
from motion.track.kernel import kernel_size_at, with_window  # noqa: E402
from motion.track.scale import estimate_scale, sample_frames  # noqa: E402
from scene.normal_sequences import SequenceConfig, head_motion, make_sequence, tau_r2  # noqa: E402
from scene.render import DEFAULT_CM_PER_PX, NeckRenderer, neck_camera, render_normals  # noqa: E402

SHARED = REPO.parent / "shared"
LIVELINK = SHARED / "samples" / "livelinkface"
BSW = SHARED / "assets" / "HACK-Model" / "data" / "bsw_list.npy"

# name: (SequenceConfig overrides); talking conditions name their recording.
CONDITIONS = {
    "still head": {"head_motion_deg": 0.0},
    "head motion 3 deg": {"head_motion_deg": 3.0},
    "head motion 6 deg": {"head_motion_deg": 6.0},
    "talking (facial.csv), 6 deg": {"head_motion_deg": 6.0, "expressions": str(LIVELINK / "facial.csv")},
    "talking (apfel.csv), 6 deg": {"head_motion_deg": 6.0, "expressions": str(LIVELINK / "apfel.csv")},
    "talking (bsw_list.npy), 6 deg": {"head_motion_deg": 6.0, "expressions": str(BSW), "expressions_fps": 30.0},
    "talking (facial.csv), 15 deg": {"head_motion_deg": 15.0, "expressions": str(LIVELINK / "facial.csv")},
    "talking (bsw_list.npy), 15 deg": {"head_motion_deg": 15.0, "expressions": str(BSW), "expressions_fps": 30.0},
    "talking (facial.csv), 6 deg, perspective 50 cm": {"head_motion_deg": 6.0, "perspective": True,
                                                        "expressions": str(LIVELINK / "facial.csv")},
    "talking (facial.csv), 6 deg, blur 1 px": {"head_motion_deg": 6.0, "blur_px": 1.0,
                                                "expressions": str(LIVELINK / "facial.csv")},
}
BASE = {"frames": 240, "noise": 0.05, "quantize_8bit": True, "swallows_per_minute": 40.0}
SCALE_CONDITIONS = ("talking (facial.csv), 6 deg", "talking (bsw_list.npy), 6 deg")
SCALE_FACTORS = (0.5, 1.0, 2.0)
FRAMING_CONDITION = "talking (facial.csv), 6 deg"
FRAMING_PX_PER_CM = (8, 12, 16, 22, 30, 40)
FRAMING_SIZES = (256, 512)


def speed(rig, kernel, neck, threads: list[int]) -> None:
    renderer = NeckRenderer(rig)
    sequence = make_sequence(rig, SequenceConfig(frames=150, swallows_per_minute=8.0, quantize_8bit=True), seed=0)
    frames = list(sequence.normals)
    init = tuple(sequence.larynx_px[0])
    encoded = [np.rint(encode_normals(n) * 255).astype(np.uint8) for n in frames]
    batch = 32
    theta = rig.from_anatomical(torch.tensor(head_motion(batch, 30.0, 0, 3.0, 0.3, rig.num_joints),
                                             dtype=torch.float32))
    tau = torch.linspace(-0.02, 0.06, batch)
    with torch.no_grad():
        vertices = rig(theta, tau=tau)

    def from_bytes():
        decoded = []
        for i, image in enumerate(encoded):
            normals = decode_frame(stored_to_unit(image)[0], False)
            check_normal_map(normals, f"frame {i}")
            decoded.append(normals)
        track_sequence(decoded, kernel, init=init, neck=neck)

    for count in threads:
        torch.set_num_threads(count)
        cv2.setNumThreads(count)
        print(f"--- {count} thread(s)")
        full, _ = frames_per_second(lambda: renderer(theta, tau=tau), batch, 3, warmup=1)
        raster, _ = frames_per_second(lambda: render_normals(vertices, renderer.faces, renderer.camera), batch, 3, 1)
        print(f"renderer 256x256: {full:.0f} frames/s with the rig's forward pass, {raster:.0f} frames/s "
              f"rasterising posed meshes")
        plain, plain_cpu = frames_per_second(lambda: track_sequence(frames, kernel, init=init), len(frames), 3)
        necked, necked_cpu = frames_per_second(lambda: track_sequence(frames, kernel, init=init, neck=neck),
                                               len(frames), 3)
        print(f"tracker 256x256: {plain:.0f} frames/s ({plain_cpu:.0f} per CPU second) without the neck, "
              f"{necked:.0f} ({necked_cpu:.0f}) with the neck's motion and compensation (target >= 300)")
        whole, _ = frames_per_second(from_bytes, len(frames), 2, warmup=1)
        print(f"tracker from 8-bit RGB frames (decode + validation + tracking with the neck): {whole:.0f} frames/s")
        base, _ = frames_per_second(lambda: [raw_correlation_argmax(n, kernel) for n in frames[:60]], 60, 2, 1)
        print(f"baseline (raw correlation over the whole frame): {base:.0f} frames/s")


def slide(rig, kernel) -> None:
    renderer = NeckRenderer(rig)
    tau = torch.linspace(-0.03, 0.06, 13)
    render, truth = renderer.render_with_truth(rig.neutral(len(tau)), tau=tau)
    truth = truth.numpy().astype(np.float64)
    rest = int(torch.argmin(tau.abs()))
    true_rise = truth[rest, 1] - truth[:, 1]
    print("larynx slide, noise-free, head still, tau -0.03..0.06 (tracked rise / the larynx point's):")
    centred = with_window(kernel, 0, 14)
    for name, variant in (("tracker (calibrated window)", kernel), ("window centred, 20x14", centred)):
        track = track_sequence(list(render.normals.numpy()), variant)
        rise = track.y[rest] - track.y
        err = np.hypot(track.x - truth[:, 0], track.y - truth[:, 1])
        print(f"  {name:30s} slope {np.polyfit(true_rise, rise, 1)[0]:.3f}  error median {np.median(err):.2f} "
              f"max {err.max():.2f} px")


def variants(kernel, neck) -> dict:
    """name -> (kernel, config, neck model, compensate) of the tracker configurations compared."""
    default = TrackerConfig()
    former = TrackerConfig(bandpass=BandpassConfig(lowpass_sigma_px=3.0))
    no_jaw = None if neck is None else dataclasses.replace(neck, offsets=neck.offsets[~neck.free],
                                                           free=neck.free[~neck.free], _weights={},
                                                           features=_drop_free(neck))
    return {"raw": (kernel, default, neck, False), "compensated": (kernel, default, neck, True),
            "before issue 16": (with_window(kernel, 0, 14), former, None, False),
            "uncalibrated window (raw)": (with_window(kernel, 0, 14), default, neck, False),
            "low-pass 3 px (raw)": (kernel, former, neck, False),
            "band not following the neck (raw)": (kernel, dataclasses.replace(
                default, neck=dataclasses.replace(default.neck, follow=False)), neck, False),
            "without the jaw's patch (compensated)": (kernel, default, no_jaw, True)}


def _drop_free(neck: NeckModel) -> np.ndarray:
    """The neck model's training features without the jaw patch's columns."""
    keep = np.repeat(~neck.free, 2)
    return neck.features[:, np.concatenate([keep, keep, [True, True]])]


def conditions(rig, kernel, neck, frames: int, seeds: int, ablations: bool) -> None:
    names = ["raw", "compensated", "before issue 16"]
    tried = variants(kernel, neck)
    if ablations:
        names += [n for n in tried if n not in names]
    print(f"R^2 of tau from the rise in pixels, {frames} frames, 256x256, noise 0.05, 8-bit, 40 swallows/min "
          f"(ceiling = the true image position):")
    print(f"  {'condition':48s} seed ceiling  " + "  ".join(f"{n[:14]:>14s}" for n in names) + "  baseline  err px")
    for condition, overrides in CONDITIONS.items():
        recording = overrides.get("expressions")
        if recording and not Path(recording).is_file():
            print(f"  {condition:48s} skipped: {recording} not found")
            continue
        for seed in range(seeds):
            config = SequenceConfig(**{**BASE, "frames": frames, **overrides})
            started = time.perf_counter()
            seq = make_sequence(rig, config, seed=seed)
            rendered = time.perf_counter() - started
            init = tuple(seq.larynx_px[0])
            scores, error = [], float("nan")
            for name in names:
                variant_kernel, cfg, variant_neck, compensate = tried[name]
                track = track_sequence(seq.normals, variant_kernel, cfg, init=init, neck=variant_neck)
                rise = track.y[0] - track.y
                if compensate:
                    rise = rise + track.neck[:, 1] - track.neck[0, 1]
                scores.append(tau_r2(seq.tau, rise))
                if name == "raw":
                    error = float(np.median(np.hypot(track.x - seq.larynx_px[:, 0], track.y - seq.larynx_px[:, 1])))
            base = np.array([raw_correlation_argmax(n, kernel) for n in seq.normals])
            print(f"  {condition:48s} {seed:4d} {seq.ceiling_r2():7.3f}  " + "  ".join(f"{s:14.3f}" for s in scores)
                  + f"  {tau_r2(seq.tau, -base[:, 1]):8.3f}  {error:6.2f}   ({rendered:.0f} s to render)", flush=True)


def tracked_r2(rig, seq, cm_per_px: float) -> tuple[float, float]:
    """(raw, compensated) R^2 of the tracker set up at ``cm_per_px`` as the CLI sets it up."""
    config = TrackerConfig().at_scale(cm_per_px)
    kernel = calibrate_window(rig_kernel(rig, cm_per_px, kernel_size_at(cm_per_px)), rig, config)
    neck = NeckModel.from_rig(rig, neck_camera(rig, cm_per_px=cm_per_px), config.neck)
    track = track_sequence(seq.normals, kernel, config, init=tuple(seq.larynx_px[0]), neck=neck)
    rise = track.y[0] - track.y
    return tau_r2(seq.tau, rise), tau_r2(seq.tau, rise + track.neck[:, 1] - track.neck[0, 1])


def scales(rig, frames: int, seeds: int) -> None:
    print(f"tracking at an unknown scale: R^2 of tau from the rise (raw / compensated), {frames} frames, the "
          f"view of 256 px at 0.08 cm/px, noise 0.05, 8-bit, 40 swallows/min:")
    print(f"  {'condition':34s} seed  scale cm/px  size  ceiling  true scale     estimated      estimate  error   time")
    for condition in SCALE_CONDITIONS:
        overrides = CONDITIONS[condition]
        recording = overrides.get("expressions")
        if recording and not Path(recording).is_file():
            print(f"  {condition:34s} skipped: {recording} not found")
            continue
        for seed in range(seeds):
            for factor in SCALE_FACTORS:
                true = DEFAULT_CM_PER_PX * factor
                size = int(round(256 / factor))
                seq = make_sequence(rig, SequenceConfig(**{**BASE, "frames": frames, **overrides, "cm_per_px": true,
                                                           "size": size}), seed=seed)
                started = time.perf_counter()
                estimate = estimate_scale(sample_frames(seq.normals), rig)
                elapsed = time.perf_counter() - started
                given = tracked_r2(rig, seq, true)
                found = tracked_r2(rig, seq, estimate.cm_per_px)
                print(f"  {condition:34s} {seed:4d}  {true:11.3f}  {size:4d}  {seq.ceiling_r2():7.3f}  "
                      f"{given[0]:.3f} / {given[1]:.3f}  {found[0]:.3f} / {found[1]:.3f}  {estimate.cm_per_px:8.4f}  "
                      f"{100 * (estimate.cm_per_px / true - 1):+5.1f}%  {elapsed:4.1f} s", flush=True)


def cli_run(rig_arg: str | None, seq) -> tuple[float, str]:
    """(seconds, the printed scale line) of ``python -m motion.track`` in-process on the sequence written as
    8-bit PNG-encoded values in a .npy, without ``cm_per_px=``, given the larynx's first position (``init_x``,
    ``init_y``: the search for it is not what is timed)."""
    import contextlib
    import io

    from base.cli import compose_config
    from base.files import save_npy
    from motion.track import run

    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "seq.npy"
        save_npy(path, np.rint(encode_normals(seq.normals) * 255).astype(np.uint8))
        x, y = seq.larynx_px[0]
        args = [f"input={path}", f"out={Path(tmp) / 't.csv'}", "plot=null", "progress=false", f"init_x={x}",
                f"init_y={y}"]
        if rig_arg:
            args.append(f"rig={rig_arg}")
        printed = io.StringIO()
        started = time.perf_counter()
        with contextlib.redirect_stdout(printed):
            run(compose_config("track", args))
        elapsed = time.perf_counter() - started
    line = next((x for x in printed.getvalue().splitlines() if x.startswith("scale:")), "")
    return elapsed, line


def framing(rig, rig_arg: str | None, frames: int, sizes: tuple[int, ...] = FRAMING_SIZES,
            densities: tuple[int, ...] = FRAMING_PX_PER_CM, cli: tuple[int, ...] = FRAMING_PX_PER_CM) -> None:
    overrides = CONDITIONS[FRAMING_CONDITION]
    recording = overrides.get("expressions")
    if recording and not Path(recording).is_file():
        print(f"framing sweep skipped: {recording} not found")
        return
    print(f"framing sweep: {FRAMING_CONDITION}, seed 0, {frames} frames, noise 0.05, 8-bit, 40 swallows/min; "
          f"R^2 of tau from the rise (raw / compensated):")
    print(f"  {'size':>4s} {'px/cm':>5s}  view cm  ceiling  true scale     estimated      estimate   error  "
          f"score  est. time (CPU s)  motion.track run")
    for size in sizes:
        for px_per_cm in densities:
            true = 1.0 / px_per_cm
            seq = make_sequence(rig, SequenceConfig(**{**BASE, "frames": frames, **overrides, "cm_per_px": true,
                                                       "size": size}), seed=0)
            given = tracked_r2(rig, seq, true)
            head = (f"  {size:4d} {px_per_cm:5d}  {size * true:7.1f}  {seq.ceiling_r2():7.3f}  "
                    f"{given[0]:.3f} / {given[1]:.3f}  ")
            started, cpu = time.perf_counter(), time.process_time()
            try:
                estimate = estimate_scale(sample_frames(seq.normals), rig)
            except InputError as error:
                print(head + f"refused ({time.perf_counter() - started:.1f} s): {error}", flush=True)
                continue
            elapsed, cpu = time.perf_counter() - started, time.process_time() - cpu
            found = tracked_r2(rig, seq, estimate.cm_per_px)
            whole = ""
            if size >= 512 and px_per_cm in cli:
                try:
                    seconds, line = cli_run(rig_arg, seq)
                    whole = f"{seconds:5.1f} s ({line.split(',')[0]})"
                except InputError as error:
                    whole = f"refused: {error}"
            print(head + f"{found[0]:.3f} / {found[1]:.3f}  {estimate.cm_per_px:9.5f}  "
                  f"{100 * (estimate.cm_per_px / true - 1):+5.1f}%  {estimate.score:5.2f}  {elapsed:5.2f} s "
                  f"({cpu:.2f} CPU)  {whole}",
                  flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", default="1", help="thread counts to time, comma separated")
    parser.add_argument("--seeds", type=int, default=1)
    parser.add_argument("--frames", type=int, default=240)
    parser.add_argument("--rig", help="rig file from python -m data.assets (default: the built-in rig)")
    parser.add_argument("--sections", default="speed,slide,conditions,ablations")
    parser.add_argument("--sizes", default="256,512", help="frame sides of the framing sweep, comma separated")
    parser.add_argument("--px-per-cm", default=",".join(map(str, FRAMING_PX_PER_CM)),
                        help="pixel densities of the framing sweep, comma separated")
    parser.add_argument("--cli-px-per-cm", default=",".join(map(str, FRAMING_PX_PER_CM)),
                        help="pixel densities at which the framing sweep times the whole motion.track run")
    args = parser.parse_args()
    sections = set(args.sections.split(","))
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    rig = HeadNeckModel.from_config(args.rig)
    print(f"rig: {rig.rig.source} ({rig.num_vertices} vertices)")
    started = time.perf_counter()
    kernel = calibrate_window(rig_kernel(rig), rig)
    calibrated = time.perf_counter()
    neck = NeckModel.from_rig(rig)
    print(f"window calibrated on the rig: offset {kernel.window[0]:g} px, sigma_y {kernel.window[1]:g} px "
          f"({calibrated - started:.1f} s); neck model: {len(neck.offsets)} patches, {int(neck.free.sum())} on the "
          f"jaw ({time.perf_counter() - calibrated:.1f} s)")
    if "speed" in sections:
        speed(rig, kernel, neck, [int(t) for t in args.threads.split(",")])
    torch.set_num_threads(1)
    cv2.setNumThreads(1)
    if "slide" in sections:
        slide(rig, kernel)
    if "conditions" in sections or "ablations" in sections:
        conditions(rig, kernel, neck, args.frames, args.seeds, "ablations" in sections)
    if "scale" in sections:
        scales(rig, args.frames, args.seeds)
    if "framing" in sections:
        framing(rig, args.rig, args.frames, tuple(int(v) for v in args.sizes.split(",")),
                tuple(int(v) for v in args.px_per_cm.split(",")), tuple(int(v) for v in args.cli_px_per_cm.split(",")))


if __name__ == "__main__":
    main()
