"""GLB, HTML, FBX and USD export time and preview-video speed.

    python benchmarks/bench_export.py [--rig rig.npz] [--second-rig other.npz] [--seconds 10]
        [--export-seconds 60] [--docs] [--usd-only]

On a synthetic 30 fps clip (nods, turns and tilts at every joint, speech-like mouth shapes, a sliding
larynx): the time to build and write the GLB (and to check it against the rig at every frame), its
size and morph-target counts; then preview frames per second (pose + render + strip + mp4 encoding,
through ``scene.preview.write_preview``) at 256x256 and 512x512 for one character and at 256x256 side
by side (the second character: ``--second-rig``, else the same rig again).  Real time is 30 frames/s.
Then the time and size of ``viewer.html`` (``scene.viewer``) and ``anim.fbx`` (``scene.fbx``, through
Blender; skipped, saying so, without it) for a clip of ``--export-seconds`` (the issue's bound: a minute
in under 30 s each).  USD (``scene.usd``): the time and size of ``anim.usdc`` and ``anim.usdz`` for the
``--export-seconds`` clip (the issue's bound: a minute in under 10 s on the built-in rig), then on a
300-frame clip with weights outside [0, 1] (jawOpen -0.2 .. 1.2, eta up to 1.25) ``UsdSkel.BakeSkinning``'s
mesh against the rig at every frame, USD's validators, and, where ``$HACKNECK_BPY_PYTHON`` names a Python
with the ``bpy`` wheel, Blender's USD importer at three frames (tests/blender_usd_reader.py);
``--usd-only`` runs just these.
``--docs`` also writes ``docs/preview_human.png`` (frame 2.0 s of the clip, three-quarter view, 256);
``--docs-only`` writes just that.
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from timing import frames_per_second  # noqa: E402

from base.files import atomic_path  # noqa: E402
from data.params import AnimationParams, rig_checksum  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402
from scene.fbx import BlenderMissing, export_fbx  # noqa: E402
from scene.gltf import build_glb, export_glb, rig_vertices  # noqa: E402
from scene.preview import Panel, preview_image, write_preview  # noqa: E402
from scene.usd import baked_points, export_usd, time_codes, validation_errors  # noqa: E402
from scene.viewer import build_viewer  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
MOUTH = ("jawOpen", "mouthFunnel", "mouthSmile_L", "mouthSmile_R", "mouthClose")


def demo_clip(rig: HeadNeckModel, seconds: float = 10.0, fps: float = 30.0) -> AnimationParams:
    """A clip: turns, nods and tilts shared over the joints (anatomical frames), speech-like mouth shapes,
    blinks, a larynx sliding +-0.02 with a swallow-like excursion."""
    t = np.arange(int(round(seconds * fps))) / fps
    anatomical = np.zeros((len(t), rig.num_joints, 3))
    anatomical[..., 0] = (0.05 * np.sin(2 * np.pi * 0.23 * t))[:, None]          # nod
    anatomical[..., 1] = (0.06 * np.sin(2 * np.pi * 0.11 * t + 0.7))[:, None]    # turn
    anatomical[..., 2] = (0.03 * np.sin(2 * np.pi * 0.17 * t + 1.9))[:, None]    # tilt
    theta = rig.from_anatomical(torch.tensor(anatomical, dtype=torch.float32))
    psi = np.zeros((len(t), len(rig.expression_names)))
    for k, name in enumerate(MOUTH):
        psi[:, rig.expression_names.index(name)] = np.clip(0.5 * np.sin(2 * np.pi * (3.1 + 0.7 * k) * t + k), 0, 1)
    for name in ("eyeBlink_L", "eyeBlink_R"):
        psi[:, rig.expression_names.index(name)] = np.exp(-0.5 * (((t % 3.3) - 1.0) / 0.06) ** 2)
    tau = 0.015 * np.sin(2 * np.pi * 0.3 * t) + 0.02 * np.exp(-0.5 * ((t - seconds * 0.6) / 0.25) ** 2)
    with torch.no_grad():
        head = rig.head_rotation(theta)
    return AnimationParams(time=t, fps=fps, psi=psi, tau=tau, eta=np.ones(len(t)), theta=theta.numpy(),
                           head_rotation=head.numpy(), joint_names=rig.joint_names,
                           expression_names=rig.expression_names, rig_checksum=rig_checksum(rig.rig))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rig", default=None, help="rig file (default: the built-in rig)")
    parser.add_argument("--second-rig", default=None, help="the side-by-side character (default: --rig again)")
    parser.add_argument("--seconds", type=float, default=10.0)
    parser.add_argument("--preview-frames", type=int, default=60)
    parser.add_argument("--export-seconds", type=float, default=60.0, help="clip length for HTML and FBX export")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--docs", action="store_true", help="write docs/preview_human.png")
    parser.add_argument("--docs-only", action="store_true", help="write docs/preview_human.png, no timing")
    parser.add_argument("--usd-only", action="store_true", help="only the USD figures")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    rig = HeadNeckModel.from_config(args.rig)
    params = demo_clip(rig, args.seconds)
    if args.docs_only:
        write_docs_frame(rig, params)
        return
    if args.usd_only:
        usd_figures(rig, args.export_seconds)
        return
    name = args.rig or "built-in rig"
    print(f"{name}: {rig.num_vertices} vertices, clip {len(params)} frames at {params.fps:g} fps, "
          f"{torch.get_num_threads()} thread(s)")
    with tempfile.TemporaryDirectory() as folder:
        started = time.perf_counter()
        report = export_glb(params, rig, Path(folder) / "clip.glb", check=False)
        export_seconds = time.perf_counter() - started
        started = time.perf_counter()
        checked = build_glb(params, rig, check=True).report
        check_seconds = time.perf_counter() - started - checked.seconds
    print(f"GLB export: {export_seconds:.2f} s for {len(params)} frames ({report.bytes / 1e6:.1f} MB; "
          f"{report.vertices} vertices, {report.expression_targets} + {report.larynx_targets} larynx + "
          f"{report.corrective_targets} corrective morph targets, larynx error {report.larynx_error_cm:.4f} cm); "
          f"checking every frame against the rig: {check_seconds:.2f} s more, max error {checked.max_error_cm:.4f} cm")
    checked4 = build_glb(params, rig, max_influences=4, check=True).report
    print(f"  max_influences=4: {checked4.truncated} vertices lose weight, max error {checked4.max_error_cm:.4f} cm")

    second = HeadNeckModel.from_config(args.second_rig) if args.second_rig else rig
    second_params = demo_clip(second, args.seconds) if args.second_rig else params
    cases = [("256x256, one character", [(rig, params, 256)]),
             ("512x512, one character", [(rig, params, 512)]),
             ("256x256, side by side", [(rig, params, 256), (second, second_params, 256)])]
    frames = min(args.preview_frames, len(params))
    clip = slice(0, frames)
    with tempfile.TemporaryDirectory() as folder:
        for label, specs in cases:
            panels = [Panel.create(r, _head(p, clip), size) for r, p, size in specs]
            wall, cpu = frames_per_second(lambda panels=panels: write_preview(Path(folder) / "p.mp4", panels),
                                          frames, repeats=3, warmup=1)
            print(f"preview {label}: {wall:.1f} frames/s wall ({wall / params.fps:.2f}x real time at "
                  f"{params.fps:g} fps), {cpu:.1f} frames per CPU second")
    export_timing(rig, demo_clip(rig, args.export_seconds))
    usd_figures(rig, args.export_seconds)
    if args.docs:
        write_docs_frame(rig, params)


def export_timing(rig: HeadNeckModel, params: AnimationParams) -> None:
    """Time and size of viewer.html and anim.fbx for ``params``."""
    with tempfile.TemporaryDirectory() as folder:
        html = build_viewer(params, rig, Path(folder) / "viewer.html")
        print(f"HTML viewer, {len(params)} frames: {html.seconds:.1f} s, {html.bytes / 1e6:.1f} MB "
              f"(GLB {html.glb_bytes / 1e6:.1f} MB)")
        try:
            fbx = export_fbx(params, rig, Path(folder) / "anim.fbx")
        except BlenderMissing as e:
            print(f"FBX: skipped ({e})")
            return
        print(f"FBX through Blender, {len(params)} frames: {fbx.seconds:.1f} s, "
              f"{fbx.path.stat().st_size / 1e6:.1f} MB")


def usd_figures(rig: HeadNeckModel, export_seconds: float, check_frames: int = 300) -> None:
    """USD export time and size, then USD's skinning, validators and Blender's importer against the rig."""
    clip = demo_clip(rig, export_seconds)
    with tempfile.TemporaryDirectory() as folder:
        for fmt in ("usdc", "usdz"):
            report = export_usd(clip, rig, Path(folder) / f"anim.{fmt}")
            print(f"USD ({fmt}), {len(clip)} frames: {report.seconds:.1f} s, {report.bytes / 1e6:.1f} MB "
                  f"({report.larynx_targets} larynx targets, interpolation bound {report.larynx_error_cm:.4f} cm)")
        params = demo_clip(rig, check_frames / 30.0)
        psi = params.psi.copy()
        psi[:, rig.expression_names.index("jawOpen")] = 0.5 + 0.7 * np.sin(2 * np.pi * 0.4 * params.time)
        params = dataclasses.replace(params, psi=psi, eta=1.0 + 0.25 * np.sin(2 * np.pi * 0.13 * params.time))
        path = Path(folder) / "check.usdc"
        report = export_usd(params, rig, path, check=True)
        started = time.perf_counter()
        worst = 0.0
        for start in range(0, len(params), 50):
            frames = np.arange(start, min(start + 50, len(params)))
            baked = baked_points(path, time_codes(params)[frames])
            worst = max(worst, float(np.linalg.norm(baked - rig_vertices(rig, params, frames), axis=-1).max()))
        print(f"USD check, {len(params)} frames (jawOpen -0.2 .. 1.2, eta up to 1.25): UsdSkel.BakeSkinning vs the "
              f"rig max {worst:.4f} cm at every frame ({time.perf_counter() - started:.1f} s); the stored arrays "
              f"{report.max_error_cm:.4f} cm; larynx bound {report.larynx_error_cm:.4f} cm "
              f"({report.larynx_targets} targets); validators: {len(validation_errors(path))} errors")
        bpy_python = os.environ.get("HACKNECK_BPY_PYTHON")
        if not bpy_python:
            print("Blender's USD importer: skipped (HACKNECK_BPY_PYTHON not set)")
            return
        jaw = psi[:, rig.expression_names.index("jawOpen")]
        frames = [int(len(params) * f) for f in (0.1, 0.5, 0.9)] + [int(np.argmax(jaw)), int(np.argmin(jaw))]
        subprocess.run([bpy_python, str(REPO / "tests" / "blender_usd_reader.py"), str(path),
                        str(Path(folder) / "b.npz"), *map(str, frames)], check=True, capture_output=True)
        blender = np.load(Path(folder) / "b.npz")["vertices"]
        errors = np.linalg.norm(blender - rig_vertices(rig, params, frames), axis=-1).max(axis=1)
        print("Blender's USD importer (frame = time code), max error per frame: "
              + ", ".join(f"frame {f} (jawOpen {jaw[f]:+.2f}) {e:.4f} cm" for f, e in zip(frames, errors)))


def write_docs_frame(rig: HeadNeckModel, params: AnimationParams) -> None:
    """docs/preview_human.png: the preview at 2.0 s, three-quarter view, 256 px."""
    panel = Panel.create(rig, params, 256, view="three_quarter")
    out = REPO / "docs" / "preview_human.png"
    with atomic_path(out) as tmp:
        cv2.imwrite(str(tmp), preview_image([panel], int(2.0 * params.fps)))
    print(f"wrote {out}")


def _head(params: AnimationParams, frames: slice) -> AnimationParams:
    """The first frames of a clip."""
    return AnimationParams(time=params.time[frames], fps=params.fps, psi=params.psi[frames], tau=params.tau[frames],
                           eta=params.eta[frames], theta=params.theta[frames],
                           head_rotation=params.head_rotation[frames], joint_names=params.joint_names,
                           expression_names=params.expression_names, rig=params.rig,
                           rig_checksum=params.rig_checksum, producers=params.producers)


if __name__ == "__main__":
    main()
