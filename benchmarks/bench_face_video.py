"""Face video: speed of ``python infer.py expressions=clip.mp4`` and the One Euro smoothing's jitter and lag.

    python benchmarks/bench_face_video.py [--seconds 60] [--fps 30] [--size 512] [--skip-speed] [--skip-smoothing]

Needs ../shared/assets/ICT-FaceKit (the rendered head, ``tests/face_head.py``) and ``pip install ".[video]"``.

Speed: a ``--seconds`` video at ``--fps``, ``--size`` x ``--size`` (mp4v), of the rendered head turning,
nodding, opening the jaw, blinking and puckering (90 distinct frames cycled, fresh sensor noise on each
cycle), through the whole ``run_take`` (the shipped larynx and neck models, params.npz and params.csv, no
plot).  Printed: each stage's seconds (read = decode + landmarker; decode alone measured on its own pass).
Target (issue 43): one minute at 30 fps, 512 x 512, to params.npz in under 40 s on 2 cores.

Smoothing (``face_smoothing``): jitter = the RMS frame-to-frame change of the 55 weights and of yaw, pitch
and roll (deg) on a still face with sensor noise (5 s, 256 x 256, Gaussian noise of 3 levels, then mp4v;
the first ``SETTLE`` frames skipped); lag = the shift (frames, 0.1 steps, linear interpolation) that best
aligns the smoothed track with the unsmoothed one on a moving face (jawOpen, eyeBlink, yaw, pitch), and
how much of a blink's peak is lost.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

ICT_DIR = Path(__file__).resolve().parents[2] / "shared" / "assets" / "ICT-FaceKit"
# Frames skipped before measuring jitter: MediaPipe's first frames on a face (detection, then its own
# tracking filter settling) move the weights by up to 0.4 over about 5 frames.
SETTLE = 10


def ypr_degrees(rotations: np.ndarray) -> np.ndarray:
    """[T,3] yaw, pitch, roll (deg) of rotations [T,3,3] = Ry(yaw) Rx(pitch) Rz(roll)."""
    r = np.asarray(rotations, dtype=np.float64)
    return np.degrees(np.stack([np.arctan2(r[:, 0, 2], r[:, 2, 2]), np.arcsin(-np.clip(r[:, 1, 2], -1, 1)),
                                np.arctan2(r[:, 1, 0], r[:, 1, 1])], axis=1))


def best_shift(reference: np.ndarray, delayed: np.ndarray) -> float:
    """Frames by which ``delayed`` lags ``reference`` (0.1-frame steps, linear interpolation, 0..6)."""
    frames = np.arange(len(reference), dtype=np.float64)
    shifts = np.arange(0.0, 6.01, 0.1)
    errors = [np.mean((np.interp(frames[10:], frames - s, delayed) - reference[10:]) ** 2) for s in shifts]
    return float(shifts[int(np.argmin(errors))])


def speed(args, work: Path) -> None:
    from base.cli import compose_config, to_dataclass
    from motion.face.frames import open_video
    from motion.pipeline.models import load_models
    from motion.pipeline.take import run_take
    from tests.face_head import FaceHead, known_motion, render_known_motion, write_video

    head = FaceHead(ICT_DIR, ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthPucker"), size=args.size)
    started = time.perf_counter()
    cycle = list(render_known_motion(head, known_motion(90, args.fps), noise=0.0))
    print(f"rendered {len(cycle)} distinct {args.size}x{args.size} frames in {time.perf_counter() - started:.1f} s")
    rng = np.random.default_rng(0)
    count = int(round(args.seconds * args.fps))

    def frames():
        for i in range(count):
            if i % len(cycle) == 0:
                noise = rng.normal(0, 2.0, cycle[0].shape)
            yield np.clip(cycle[i % len(cycle)] + noise, 0, 255).astype(np.uint8)

    video = write_video(work / "clip.mp4", frames(), args.fps)
    print(f"{video.name}: {count} frames, {video.stat().st_size / 1e6:.1f} MB")
    started = time.perf_counter()
    for _ in open_video(video).frames():
        pass
    decode = time.perf_counter() - started
    cfg = to_dataclass(compose_config("infer", [f"expressions={video}", f"out_dir={work / 'out'}", "audio=none",
                                                "plot=false"]), where="infer")
    models = load_models(cfg, announce=lambda message: None)
    started = time.perf_counter()
    row = run_take(cfg, models, str(video), work / "out", announce=lambda message: None)
    total = time.perf_counter() - started
    stages = row["stage_seconds"]
    print(f"end to end {total:.1f} s for {count} frames ({count / total:.1f} frames/s); decode alone {decode:.1f} s, "
          f"so the landmarker about {stages['read'] - decode:.1f} s "
          f"({1000 * (stages['read'] - decode) / count:.1f} ms a frame)")
    print("stages: " + ", ".join(f"{k} {v:.2f} s" for k, v in stages.items()))
    print(f"target: under 40 s -> {'met' if total < 40 else 'NOT met'}")


def smoothing(args, work: Path) -> None:
    from data.expressions import EXPRESSION_NAMES
    from motion.face.video import read_face_video
    from tests.face_head import FaceHead, known_motion, render_known_motion, write_video

    head = FaceHead(ICT_DIR, ("jawOpen", "eyeBlink_L", "eyeBlink_R", "mouthPucker"), size=256)
    rng = np.random.default_rng(1)
    still = head.render({"jawOpen": 0.2})
    noisy = (np.clip(still + rng.normal(0, 3.0, still.shape), 0, 255).astype(np.uint8) for _ in range(150))
    still_video = write_video(work / "still.mp4", noisy, 30.0)
    moving = known_motion(120, 30.0)
    moving_video = write_video(work / "moving.mp4", render_known_motion(head, moving, noise=2.0), 30.0)
    tracks = {}
    for smooth in (False, True):
        tracks["still", smooth] = read_face_video(still_video, smoothing=smooth, show_progress=False)
        tracks["moving", smooth] = read_face_video(moving_video, smoothing=smooth, show_progress=False)
    print("face_smoothing  weight jitter  yaw/pitch/roll jitter (deg)  lag jawOpen/eyeBlink/yaw/pitch (frames)  "
          "blink peak\n(jitter: RMS frame-to-frame change on the still face after its first frames)")
    raw_moving = tracks["moving", False]
    for smooth in (False, True):
        track = tracks["still", smooth]
        settled = slice(SETTLE, None)
        weight_jitter = float(np.sqrt(np.mean(np.diff(track.psi[settled], axis=0) ** 2)))
        pose_jitter = np.sqrt(np.mean(np.diff(ypr_degrees(track.head_rotation[settled]), axis=0) ** 2, axis=0))
        moved = tracks["moving", smooth]
        lags = []
        for name in ("jawOpen", "eyeBlink_L"):
            k = EXPRESSION_NAMES.index(name)
            lags.append(best_shift(raw_moving.psi[:, k], moved.psi[:, k]))
        raw_angles, angles = ypr_degrees(raw_moving.head_rotation), ypr_degrees(moved.head_rotation)
        lags += [best_shift(raw_angles[:, a], angles[:, a]) for a in (0, 1)]
        k = EXPRESSION_NAMES.index("eyeBlink_L")
        peak = moved.psi[:, k].max() / raw_moving.psi[:, k].max()
        print(f"{str(smooth):<15} {weight_jitter:.4f}         {' / '.join(f'{j:.3f}' for j in pose_jitter):<28} "
              f"{' / '.join(f'{lag:.1f}' for lag in lags):<40} {100 * peak:.0f}%")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--fps", type=float, default=30.0)
    parser.add_argument("--size", type=int, default=512)
    parser.add_argument("--skip-speed", action="store_true")
    parser.add_argument("--skip-smoothing", action="store_true")
    args = parser.parse_args()
    torch.set_num_threads(1)
    if not (ICT_DIR / "FaceXModel").is_dir():
        sys.exit(f"ICT-FaceKit not found in {ICT_DIR}")
    with tempfile.TemporaryDirectory() as tmp:
        if not args.skip_smoothing:
            smoothing(args, Path(tmp))
        if not args.skip_speed:
            speed(args, Path(tmp))


if __name__ == "__main__":
    main()
