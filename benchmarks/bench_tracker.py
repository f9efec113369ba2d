"""Larynx tracker and normal-map renderer: speed and accuracy on synthetic sequences.

    python benchmarks/bench_tracker.py [--threads 1,2] [--seeds 4] [--frames 150] [--rig rig.npz]

Prints, for each thread count (torch and OpenCV; the 2 cores are shared, so compare runs taken
together):
- renderer frames/s (256x256 neck view, batches of 32 frames with head motion and tau), with the rig's
  forward pass included and without it;
- tracker frames/s on 256x256 decoded frames with the search band (the target is >= 300), and the
  whole per-frame path from 8-bit RGB (decode + validation + tracking);
- the larynx slide on noise-free renders (head still, tau -0.03..0.06 in 13 steps, tracked as a
  sequence): tracked rise over the larynx point's (slope of a line fit, and per frame) and the error;
- accuracy over ``--seeds`` sequences (noise 0.05, 3 degrees of head motion, swallows): median / p95
  / max error in pixels of the tracker, of ablations (no match window; no column high-pass; no
  low-pass; the rest render as the kernel instead of the larynx's perturbation; the former matching:
  the rest render, an 81 px row high-pass alone, no window), with temporal smoothing, and of the
  baseline (integer arg-max of the raw correlation over the whole frame).
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from data.normal_sequences import SequenceConfig, head_motion, make_sequence  # noqa: E402
from data.normals import encode_normals, stored_to_unit
from data.render import NeckRenderer, render_normals
from models.rig import HeadNeckModel  # noqa: E402
from motion.track import (TrackerConfig, check_normal_map, decode_frame, raw_correlation_argmax,  # noqa: E402
                          rig_kernel, track_frames)


def best_of(run, repeats: int) -> float:
    """Shortest of ``repeats`` timings (s): the machine is shared, the minimum is the least disturbed."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", default="1,2", help="thread counts to time, comma separated")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--frames", type=int, default=150)
    parser.add_argument("--rig", help="rig file from python -m data.assets (default: the built-in rig)")
    args = parser.parse_args()
    rig = HeadNeckModel.from_config(args.rig)
    print(f"rig: {rig.rig.source} ({rig.num_vertices} vertices)")
    renderer = NeckRenderer(rig)
    kernel = rig_kernel(rig)
    sequence = make_sequence(rig, SequenceConfig(frames=300, swallows_per_minute=8.0), seed=0)
    frames = list(sequence.normals)
    encoded = [np.rint(encode_normals(n) * 255).astype(np.uint8) for n in frames]
    batch = 32
    anatomical = torch.tensor(head_motion(batch, 30.0, 0, 3.0, 0.3, rig.num_joints), dtype=torch.float32)
    theta = rig.from_anatomical(anatomical)
    tau = torch.linspace(-0.02, 0.06, batch)
    with torch.no_grad():
        vertices = rig(theta, tau=tau)

    def from_bytes():
        decoded = []
        for i, image in enumerate(encoded):
            normals = decode_frame(stored_to_unit(image)[0], False)
            check_normal_map(normals, f"frame {i}")
            decoded.append(normals)
        track_frames(decoded, kernel)

    for threads in (int(t) for t in str(args.threads).split(",")):
        torch.set_num_threads(threads)
        cv2.setNumThreads(threads)
        print(f"--- {threads} thread(s)")
        renderer(theta[:4], tau=tau[:4])
        full = best_of(lambda: renderer(theta, tau=tau), 3)
        raster = best_of(lambda: render_normals(vertices, renderer.faces, renderer.camera), 3)
        print(f"renderer 256x256: {batch / full:.0f} frames/s with the rig's forward pass "
              f"({60 * batch / full:.0f} frames per minute), {batch / raster:.0f} frames/s rasterising posed meshes")
        track_frames(frames[:10], kernel)
        seconds = best_of(lambda: track_frames(frames, kernel), 3)
        print(f"tracker 256x256, band +-{TrackerConfig().band_rows} rows +-{TrackerConfig().band_cols} cols: "
              f"{len(frames) / seconds:.0f} frames/s (target >= 300)")
        seconds = best_of(from_bytes, 2)
        print(f"tracker from 8-bit RGB frames (decode + validation + tracking): {len(frames) / seconds:.0f} frames/s")
        full_frame = best_of(lambda: [raw_correlation_argmax(n, kernel) for n in frames[:60]], 2)
        print(f"baseline (raw correlation over the whole frame): {60 / full_frame:.0f} frames/s")

    # ------------------------------------------------------------------ accuracy
    default = TrackerConfig()
    rest_render = dataclasses.replace(kernel, background=None)
    variants = {"tracker (default)": (kernel, default),
                "no match window": (kernel, dataclasses.replace(default, window_sigma_x_px=0.0)),
                "no column high-pass": (kernel, dataclasses.replace(default, column_highpass_px=0)),
                "no low-pass": (kernel, dataclasses.replace(default, lowpass_sigma_px=0.0)),
                "rest render as kernel": (rest_render, default),
                "former matching": (rest_render, dataclasses.replace(default, lowpass_sigma_px=0.0, row_highpass_px=81,
                                                                     column_highpass_px=0, window_sigma_x_px=0.0)),
                "smoothing sigma 1 frame": (kernel, dataclasses.replace(default, smooth_frames=1.0)),
                "smoothing sigma 2 frames": (kernel, dataclasses.replace(default, smooth_frames=2.0))}

    slide_tau = torch.linspace(-0.03, 0.06, 13)
    render, truth = renderer.render_with_truth(rig.neutral(len(slide_tau)), tau=slide_tau)
    truth = truth.numpy().astype(np.float64)
    rest = int(torch.argmin(slide_tau.abs()))
    true_rise = truth[rest, 1] - truth[:, 1]
    moved = np.abs(true_rise) > 1.0
    print("larynx slide, noise-free, head still, tau -0.03..0.06 (tracked rise / the larynx point's):")
    for name in ("tracker (default)", "no match window", "no column high-pass", "rest render as kernel",
                 "former matching"):
        track = track_frames(list(render.normals.numpy()), *variants[name])
        rise = track.y[rest] - track.y
        per_frame = rise[moved] / true_rise[moved]
        err = np.hypot(track.x - truth[:, 0], track.y - truth[:, 1])
        print(f"  {name:26s} slope {np.polyfit(true_rise, rise, 1)[0]:.3f}  per frame {per_frame.min():.2f}.."
              f"{per_frame.max():.2f}  error median {np.median(err):.2f}  max {err.max():.2f} px")

    errors: dict[str, list] = {name: [] for name in [*variants, "baseline raw arg-max"]}
    config = SequenceConfig(frames=args.frames, noise=0.05, head_motion_deg=3.0, swallows_per_minute=20.0)
    for seed in range(args.seeds):
        seq = make_sequence(rig, config, seed=100 + seed)
        for name, (variant_kernel, tracker_config) in variants.items():
            track = track_frames(seq.normals, variant_kernel, tracker_config)
            errors[name].append(np.hypot(track.x - seq.larynx_px[:, 0], track.y - seq.larynx_px[:, 1]))
        base = np.array([raw_correlation_argmax(n, kernel) for n in seq.normals])
        errors["baseline raw arg-max"].append(np.hypot(*(base - seq.larynx_px).T))
        print(f"  seed {100 + seed}: tau {seq.tau.min():+.3f}..{seq.tau.max():+.3f}, eta {seq.eta:.2f}")
    print(f"accuracy over {args.seeds} x {args.frames} frames (256x256, noise 0.05, 3 deg head motion), pixels:")
    for name, values in errors.items():
        e = np.concatenate(values)
        print(f"  {name:26s} median {np.median(e):.3f}  p95 {np.percentile(e, 95):.3f}  max {e.max():.2f}")


if __name__ == "__main__":
    main()
