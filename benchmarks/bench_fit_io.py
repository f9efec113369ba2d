"""What ``motion.fit`` spends around the solver: reading captures (PLY ascii / binary, OBJ) and writing a fit's
folder.  The solver's own figures are ``bench_fit.py``'s.

    OMP_NUM_THREADS=1 python benchmarks/bench_fit_io.py [--frames 60] [--points 25000] [--rig hack_rig.npz]

Prints, per format, the seconds to read one 25,000-point scan and one rig-topology frame, the frames/s of
``motion.fit.read_capture`` over a folder of ``--frames`` binary PLY frames, and the seconds to write the
fit's params.npz / params.csv / plot.png / report.json (a fit result made up from the capture's truth).
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

from data.mesh_io import read_points, write_obj, write_ply  # noqa: E402
from models.fit import FitResult  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402
from motion.fit.inputs import read_capture  # noqa: E402
from motion.fit.outputs import fit_params, fit_report, plot_fit, write_report  # noqa: E402
from motion.pipeline.config import InferConfig  # noqa: E402
from motion.pipeline.models import Models  # noqa: E402
from motion.pipeline.outputs import write_outputs  # noqa: E402


def write_folder(rig: HeadNeckModel, frames: int, folder: Path) -> dict:
    """A made-up fit of ``frames`` frames written as motion.fit writes it; seconds per part."""
    j, e, v = rig.num_joints, rig.num_expressions, rig.num_vertices
    result = FitResult(theta=np.zeros((frames, j, 3), np.float32), psi=np.zeros((frames, e), np.float32),
                       tau=np.zeros(frames, np.float32), eta=1.0, root_rotation=np.tile(np.eye(3, dtype=np.float32),
                                                                                        (frames, 1, 1)),
                       root_translation=np.zeros((frames, 3), np.float32), shape_offset=np.zeros((v, 3), np.float32),
                       fit_rms_mm=np.ones(frames, np.float32),
                       joint_uncertainty_deg=np.r_[np.nan, np.ones(j - 1)].astype(np.float32), report={})
    seconds = {}
    started = time.perf_counter()
    params = fit_params(result, rig, 30.0, "builtin", {"tool": "bench", "source": "bench"})
    write_outputs(InferConfig(plot=False), Models(rig=rig, rig_name="builtin"), params, folder)
    seconds["params.npz + params.csv"] = time.perf_counter() - started
    started = time.perf_counter()
    report = fit_report(params, result, rig, [f"f{k}" for k in range(frames)], {"fit": 1.0}, {})
    plot_fit(folder / "plot.png", params, rig, report["worst_frames"])
    seconds["plot.png"] = time.perf_counter() - started
    started = time.perf_counter()
    write_report(folder / "report.json", report)
    seconds["report.json"] = time.perf_counter() - started
    return seconds


def write_ascii_ply(path: Path, points: np.ndarray, big_endian: bool | None = None) -> None:
    """ascii (``big_endian`` None) or binary big-endian PLY of a point cloud (write_ply writes little-endian)."""
    fmt = "ascii" if big_endian is None else "binary_big_endian"
    header = (f"ply\nformat {fmt} 1.0\nelement vertex {len(points)}\nproperty float x\nproperty float y\n"
              "property float z\nend_header\n").encode()
    if big_endian is None:
        body = "".join(f"{x:.5f} {y:.5f} {z:.5f}\n" for x, y, z in points).encode()
    else:
        body = np.asarray(points, ">f4").tobytes()
    path.write_bytes(header + body)


def timed(function, repeat: int = 5) -> float:
    best = np.inf
    for _ in range(repeat):
        started = time.perf_counter()
        function()
        best = min(best, time.perf_counter() - started)
    return best


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=60)
    parser.add_argument("--points", type=int, default=25000)
    parser.add_argument("--rig", default=None)
    args = parser.parse_args()
    torch.set_num_threads(1)
    rig = HeadNeckModel.from_config(args.rig)
    rng = np.random.default_rng(0)
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        cloud = rng.normal(0, 10, (args.points, 3))
        template = rig.rig.template.astype(np.float64)
        write_ply(folder / "scan_le.ply", cloud, np.zeros((0, 3), int))
        write_ascii_ply(folder / "scan_ascii.ply", cloud)
        write_ascii_ply(folder / "scan_be.ply", cloud, big_endian=True)
        write_ply(folder / "mesh.ply", template, rig.rig.faces)
        write_obj(folder / "mesh.obj", template, rig.rig.faces)
        print(f"rig: {rig.num_vertices} vertices ({args.rig or 'builtin'})")
        for name in ("scan_le.ply", "scan_be.ply", "scan_ascii.ply", "mesh.ply", "mesh.obj"):
            seconds = timed(lambda name=name: read_points(folder / name))
            print(f"read_points {name:15s} {seconds * 1000:8.1f} ms")
        frames = folder / "frames"
        frames.mkdir()
        for k in range(args.frames):
            write_ply(frames / f"frame_{k}.ply", template * 10 + rng.normal(0, 1, template.shape), rig.rig.faces)
        seconds = timed(lambda: read_capture(str(frames), "meshes", "mm", rig.rig.template), repeat=2)
        print(f"read_capture {args.frames} binary PLY frames (kind=meshes, units=mm): {seconds:.2f} s = "
              f"{args.frames / seconds:.0f} frames/s")
        for part, seconds in write_folder(rig, args.frames, folder / "out").items():
            print(f"write {part}: {seconds:.2f} s")


if __name__ == "__main__":
    main()
