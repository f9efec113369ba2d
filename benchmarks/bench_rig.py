"""Forward-pass speed of the head-and-neck model against the release's dense per-vertex 4x4 blending.

    python benchmarks/bench_rig.py [--rig rig.npz] [--hack-assets ../shared/assets] [--threads 2]

Batch of 64 frames, all 55 expressions active, random poses and tau, CPU.
With the real release available (a rig file, or ``--hack-assets`` to convert
it on the fly) it also times the reference implementation of the release's
algorithm (tests/reference_hack.py) on the same inputs and checks agreement.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import torch

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests")]

from data.assets import RigData, convert  # noqa: E402
from data.expressions import EXPRESSION_NAMES  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402
from timing import frames_per_second  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rig", help="rig file from python -m data.assets")
    parser.add_argument("--hack-assets", default=str(REPO.parent / "shared" / "assets"),
                        help="folder with HACK-Model/ and ICT-FaceKit/ (converted on the fly)")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--repeats", type=int, default=30)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)

    assets = Path(args.hack_assets)
    have_release = (assets / "HACK-Model" / "model").is_dir() and (assets / "ICT-FaceKit").is_dir()
    if args.rig:
        start = time.perf_counter()
        rig = RigData.load(args.rig)
        print(f"rig file load: {time.perf_counter() - start:.3f} s")
    elif have_release:
        with tempfile.TemporaryDirectory() as tmp:
            start = time.perf_counter()
            convert(assets / "HACK-Model", assets / "ICT-FaceKit", Path(tmp) / "rig.npz")
            print(f"conversion of the release: {time.perf_counter() - start:.1f} s")
            start = time.perf_counter()
            rig = RigData.load(Path(tmp) / "rig.npz")
            print(f"rig file load: {time.perf_counter() - start:.3f} s")
    else:
        rig = HeadNeckModel.builtin().rig
        print("real release not found: benchmarking the built-in rig")
    model = HeadNeckModel(rig)

    g = torch.Generator().manual_seed(0)
    b = args.batch
    theta = (torch.rand(b, 8, 3, generator=g) - 0.5) * 0.4
    psi = torch.rand(b, 55, generator=g)
    tau = (torch.rand(b, generator=g) - 0.5) * 0.1
    eta = torch.ones(b)
    with torch.no_grad():
        ours, ours_cpu = frames_per_second(lambda: model(theta, psi, tau, eta), b, args.repeats, warmup=10)
    print(f"ours: {ours:,.0f} frames/s wall clock, {ours_cpu:,.0f} frames per CPU second  (batch {b}, "
          f"{model.num_vertices} vertices, 55 expressions, {args.threads} threads)")
    if have_release and not args.rig and rig.template.shape[0] == 14062:
        from reference_hack import ReleaseReference

        reference = ReleaseReference(assets / "HACK-Model", assets / "ICT-FaceKit", list(EXPRESSION_NAMES),
                                     dtype=torch.float32)
        with torch.no_grad():
            theirs, _ = frames_per_second(lambda: reference(theta, psi, tau, eta), b, max(3, args.repeats // 10))
            error = (model(theta, psi, tau, eta) - reference(theta, psi, tau, eta)).abs().max()
        print(f"release-style dense per-vertex 4x4 blending (float32): {theirs:,.0f} frames/s")
        print(f"speed-up: {ours / theirs:.1f}x; max difference {float(error):.2e} cm")

if __name__ == "__main__":
    main()
