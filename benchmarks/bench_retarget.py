"""Retargeting speed: a 1,000-frame clip from the real HACK rig onto its giraffe, retargeted and posed.

    python benchmarks/bench_retarget.py [--rig rig.npz] [--hack-assets ../shared/assets] [--frames 1000]
        [--batch 64] [--threads 2] [--repeats 3]

The clip: random cervical poses inside the human joint limits, 10 % of the 55 expressions active, tau and
eta varying, at 30 fps.  Timed per pass over the whole clip: the retarget (anatomical frames, giraffe gains,
clamping to the giraffe's limits; ``motion.retarget.retarget_params``) and posing every frame on the giraffe
(``motion.retarget.pose``) with linear blend skinning and, where ``models.rig`` has it, dual quaternions.
Meshes are not written (disk speed is not the rig's).  Without the release (``../shared/assets``) it says so
and falls back to the built-in rig.  Building the giraffe (once per character) is timed separately.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "benchmarks")]

from timing import frames_per_second  # noqa: E402

from base.rotations import euler_to_axis_angle  # noqa: E402
from data.assets import RigData, convert  # noqa: E402
from data.joint_limits import euler_limits  # noqa: E402
from data.params import AnimationParams, rig_checksum  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402
from motion.retarget import GIRAFFE_GAINS, pose, retarget_params, supports_skinning  # noqa: E402
from scene.characters import build_giraffe  # noqa: E402


def source_rig(args) -> tuple[RigData, str]:
    assets = Path(args.hack_assets)
    if args.rig:
        return RigData.load(args.rig), f"rig file {args.rig}"
    if (assets / "HACK-Model" / "model").is_dir() and (assets / "ICT-FaceKit").is_dir():
        with tempfile.TemporaryDirectory() as tmp:
            convert(assets / "HACK-Model", assets / "ICT-FaceKit", Path(tmp) / "rig.npz")
            return RigData.load(Path(tmp) / "rig.npz"), f"the real HACK release ({assets})"
    print(f"skip: the real HACK release is not in {assets} (../shared absent); benchmarking the built-in rig")
    return HeadNeckModel.builtin().rig, "the built-in rig"


def clip(rig: HeadNeckModel, frames: int, seed: int = 0) -> AnimationParams:
    generator = torch.Generator().manual_seed(seed)
    lower, upper = euler_limits(0.9)
    theta = rig.from_anatomical(euler_to_axis_angle(lower + (upper - lower) * torch.rand(frames, 8, 3,
                                                                                          generator=generator)))
    rng = np.random.default_rng(seed)
    psi = rng.uniform(0, 1, (frames, 55)) * (rng.uniform(size=(frames, 55)) < 0.1)
    with torch.no_grad():
        head = rig.head_rotation(theta).numpy()
    return AnimationParams(time=np.arange(frames) / 30.0, fps=30.0, psi=psi, tau=rng.uniform(-0.02, 0.05, frames),
                           eta=rng.uniform(0.7, 1.3, frames), theta=theta.numpy(), head_rotation=head,
                           joint_names=rig.joint_names, expression_names=rig.expression_names, rig="bench",
                           rig_checksum=rig_checksum(rig.rig))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rig", help="rig file from python -m data.assets")
    parser.add_argument("--hack-assets", default=str(REPO.parent / "shared" / "assets"))
    parser.add_argument("--frames", type=int, default=1000)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    rig_data, where = source_rig(args)
    source = HeadNeckModel(rig_data)
    start = time.perf_counter()
    giraffe = HeadNeckModel(build_giraffe(rig_data))
    print(f"source: {where}, {source.num_vertices} vertices; giraffe built in {time.perf_counter() - start:.1f} s")
    params = clip(source, args.frames)

    def retarget() -> AnimationParams:
        return retarget_params(params, source, giraffe, "giraffe", GIRAFFE_GAINS)

    retargeted = retarget()
    fps, cpu_fps = frames_per_second(retarget, args.frames, args.repeats, warmup=1)
    print(f"{args.frames} frames, batch {args.batch}, {args.threads} thread(s); frames/s (wall, per CPU second):")
    print(f"  retarget only          {fps:10.0f} {cpu_fps:10.0f}")
    for skinning in ("lbs", "dqs"):
        if not supports_skinning(giraffe, skinning):
            print(f"  retarget + pose {skinning.upper()}   (models.rig has no skinning='{skinning}' yet)")
            continue

        def run(skinning=skinning) -> None:
            result = retarget()
            for _ in pose(giraffe, result, skinning, args.batch):
                pass

        fps, cpu_fps = frames_per_second(run, args.frames, args.repeats, warmup=1)
        print(f"  retarget + pose {skinning.upper()}   {fps:10.0f} {cpu_fps:10.0f}")
    assert len(retargeted) == args.frames


if __name__ == "__main__":
    main()
