"""Fitting HACK to captures (issue 55): accuracy and speed of ``models.fit`` on synthetic captures.

    python benchmarks/bench_fit.py [--rig builtin|hack_rig.npz] [--regimes meshes,scans,person]
        [--sequences 2] [--seconds 3] [--seed 0] [--out results.json]

Sequences: cervical motion from ``data.cervical_prior.sample_sequences`` (the rig's bone frames through
``rig.from_anatomical``), expressions from ``../shared/assets/HACK-Model/data/bsw_list.npy`` (a window at a
random offset; the built-in demo take when absent), tau from ``models/pretrained/swallow_template.csv`` (one
swallow at a random time on a slow drift), eta uniform in [0.8, 1.1], a slowly swaying placement (a random
rotation for meshes; facing the scanner, +z, within 15 degrees for scans), 1 mm Gaussian noise per axis.
Regimes:

- meshes: the noisy meshes in the rig's topology;
- scans: ``data.fit_captures.scan_sequence``: 25,000 points a frame in mm (converted to cm as ``motion.fit``
  does), front half, three 3 cm holes, 1 mm noise, 3 % strays;
- person: the meshes of another person (``data.fit_captures.reshaped_person``), ``fit_shape=True``.

Each regime: the fit (default ``FitSettings``), a per-frame baseline (no temporal term, no E_rot, every frame
from its own initial placement: no warm start), and a bound: meshes, the fit started at the truth; scans,
known correspondences (``fit_meshes`` on the same frames' vertices, the front-facing ones only, 1 mm
noise); person, the person's rest shape known (the rig rebuilt on it).  Scores: joints (geodesic angle in
bone frames, mean over frames and c6c7..oc1, degrees), head (angle between root_rotation @ head_rotation and
the true world head orientation, degrees), tau RMSE, vertices (RMS distance of the fitted mesh to the clean
one, mm), frames/s (wall clock, and per CPU second of this process / threads: what idle cores would do).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from base.rotations import axis_angle_to_matrix, matrix_to_axis_angle, relative_angle  # noqa: E402
from data.cervical_prior import PriorConfig, sample_sequences  # noqa: E402
from data.fit_captures import ScanConfig, reshaped_person, scan_sequence  # noqa: E402
from data.mesh_io import triangulate, vertex_normals  # noqa: E402
from models.fit import FitSettings, fit_meshes, fit_scans  # noqa: E402
from models.fit.meshes import MeshData, fit_weighted_meshes  # noqa: E402
from models.fit.sequence import fit_sequence, initial_state  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
BSW = REPO.parent / "shared" / "assets" / "HACK-Model" / "data" / "bsw_list.npy"
SWALLOW = REPO / "models" / "pretrained" / "swallow_template.csv"
NOISE_CM = 0.1


@dataclasses.dataclass
class Truth:
    theta: torch.Tensor      # [T,J,3] bone frames
    psi: torch.Tensor
    tau: torch.Tensor
    eta: float
    rotation: torch.Tensor   # [T,3,3]
    translation: torch.Tensor
    clean: torch.Tensor      # [T,V,3] cm, capture frame
    noisy: torch.Tensor


def expressions(frames: int, rng: np.random.Generator) -> np.ndarray:
    if BSW.is_file():
        bsw = np.load(BSW).astype(np.float32)
        start = int(rng.integers(0, len(bsw) - frames))
        return bsw[start: start + frames]
    from data.demo_take import demo_take

    psi = demo_take(30.0, seed=int(rng.integers(1 << 16))).psi.astype(np.float32)
    start = int(rng.integers(0, max(1, len(psi) - frames)))
    return np.resize(psi[start:], (frames, psi.shape[1]))


def larynx(frames: int, fps: float, rng: np.random.Generator) -> np.ndarray:
    table = np.genfromtxt(SWALLOW, delimiter=",", names=True)
    onset = rng.uniform(0.1, 0.6) * frames / fps
    time_axis = np.arange(frames) / fps - onset
    swallow = np.interp(time_axis, table["time"], table["tau"], left=table["tau"][0], right=table["tau"][-1])
    drift = 0.003 * np.sin(2 * np.pi * (np.arange(frames) / fps) / rng.uniform(4, 8) + rng.uniform(0, 6.3))
    return (swallow + drift).astype(np.float32)


def random_rotation(rng: np.random.Generator) -> torch.Tensor:
    q = rng.normal(size=4)
    w, x, y, z = q / np.linalg.norm(q)
    return torch.tensor([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                         [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                         [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]], dtype=torch.float32)


def make_truth(model: HeadNeckModel, theta_anatomical: np.ndarray, fps: float, rng: np.random.Generator,
               facing_scanner: bool) -> Truth:
    frames = len(theta_anatomical)
    theta = model.from_anatomical(torch.tensor(theta_anatomical))
    psi = torch.tensor(expressions(frames, rng))
    tau = torch.tensor(larynx(frames, fps, rng))
    eta = float(rng.uniform(0.8, 1.1))
    t = torch.arange(frames, dtype=torch.float32) / fps
    if facing_scanner:
        base = axis_angle_to_matrix(torch.tensor(rng.uniform(-1, 1, 3) * math.radians(15), dtype=torch.float32))
    else:
        base = random_rotation(rng)
    axis = torch.tensor(rng.normal(size=3), dtype=torch.float32)
    axis = axis / axis.norm()
    period = float(rng.uniform(3, 6))
    sway = axis_angle_to_matrix(axis * math.radians(4) * torch.sin(2 * math.pi * t / period)[:, None])
    rotation = base @ sway
    translation = (torch.tensor(rng.normal(0, 20, 3), dtype=torch.float32)
                   + torch.sin(2 * math.pi * t[:, None] / period + torch.tensor([0.0, 1.0, 2.0])))
    with torch.no_grad():
        posed = model(theta, psi, tau, torch.full((frames,), eta))
    clean = posed @ rotation.transpose(1, 2) + translation[:, None]
    generator = torch.Generator().manual_seed(int(rng.integers(1 << 31)))
    noisy = clean + NOISE_CM * torch.randn(clean.shape, generator=generator)
    return Truth(theta, psi, tau, eta, rotation, translation, clean, noisy)


def fitted_vertices(model: HeadNeckModel, result) -> torch.Tensor:
    if result.shape_offset is not None:
        rig = dataclasses.replace(model.rig, template=model.rig.template + result.shape_offset)
        model = HeadNeckModel(rig)
    frames = len(result.theta)
    with torch.no_grad():
        posed = model(torch.tensor(result.theta), torch.tensor(result.psi), torch.tensor(result.tau),
                      torch.full((frames,), result.eta))
    return posed @ torch.tensor(result.root_rotation).transpose(1, 2) + torch.tensor(result.root_translation)[:, None]


def scores(model: HeadNeckModel, truth: Truth, result, seconds: float, cpu_seconds: float,
           truth_model: HeadNeckModel | None = None) -> dict:
    theta = torch.tensor(result.theta)
    joints = relative_angle(axis_angle_to_matrix(theta[:, 1:]), axis_angle_to_matrix(truth.theta[:, 1:]))
    head_true = truth.rotation @ (truth_model or model).head_rotation(truth.theta)
    head_fit = torch.tensor(result.root_rotation) @ model.head_rotation(theta)
    vertices = fitted_vertices(model, result)
    frames = len(theta)
    threads = torch.get_num_threads()
    return {"joints_deg": math.degrees(float(joints.mean())),
            "joints_per_level_deg": [round(math.degrees(float(x)), 3) for x in joints.mean(0)],
            "head_deg": math.degrees(float(relative_angle(head_true, head_fit).mean())),
            "tau_rmse": float(((torch.tensor(result.tau) - truth.tau) ** 2).mean().sqrt()),
            "eta_error": abs(result.eta - truth.eta),
            "vertices_mm": 10 * float(((vertices - truth.clean) ** 2).sum(-1).mean().sqrt()),
            "fps_wall": frames / seconds, "fps_cpu": frames / max(cpu_seconds / threads, 1e-9),
            "uncertainty_deg": [round(float(x), 3) for x in result.joint_uncertainty_deg]}


def timed(fn):
    start, start_cpu = time.perf_counter(), time.process_time()
    result = fn()
    return result, time.perf_counter() - start, time.process_time() - start_cpu


BASELINE = dict(temporal=False, limit_deg=0.0, neck_prior="none")


def run_meshes(model: HeadNeckModel, truth: Truth) -> dict:
    out = {}
    noisy = truth.noisy.numpy()
    result, wall, cpu = timed(lambda: fit_meshes(model, noisy))
    out["fit"] = scores(model, truth, result, wall, cpu)
    result, wall, cpu = timed(lambda: fit_meshes(model, noisy, FitSettings(neck_prior="none")))
    out["fit_no_neck_prior"] = scores(model, truth, result, wall, cpu)
    result, wall, cpu = timed(lambda: fit_meshes(model, noisy, FitSettings(**BASELINE)))
    out["per_frame"] = scores(model, truth, result, wall, cpu)
    # Bound: the fit started at the truth (no local minimum, the same energy).
    state = initial_state(model, truth.rotation, truth.translation)
    state.rigid = root_folded(model, truth)
    state.rigid[:, 0:3] = matrix_to_axis_angle(rigid_rotation(model, truth) @ state.reference.T)
    state.psi, state.tau, state.eta = truth.psi.clone(), truth.tau.clone(), torch.tensor([truth.eta])
    settings = FitSettings(iterations=(0, 0, 4))
    result, wall, cpu = timed(lambda: fit_sequence(model, MeshData(truth.noisy), state, settings))
    out["bound"] = scores(model, truth, result, wall, cpu)
    return out


def rigid_rotation(model: HeadNeckModel, truth: Truth) -> torch.Tensor:
    """The placement with the root joint's rotation folded in: R @ (c7t1's rest-to-posed rotation)."""
    root = model.joint_transforms(truth.theta)[:, 0, :3, :3] @ model.rest_world[0, :3, :3].T
    return truth.rotation @ root


def root_folded(model: HeadNeckModel, truth: Truth) -> torch.Tensor:
    """rigid [T, 6 + 3(J-1)] of the truth with c7t1 folded into the placement (rotation filled by the caller)."""
    frames = len(truth.theta)
    bones = model.joint_transforms(truth.theta) @ model.rest_world_inverse
    shift = (truth.rotation @ bones[:, 0, :3, 3:])[..., 0] + truth.translation
    return torch.cat([torch.zeros(frames, 3), shift, truth.theta[:, 1:].reshape(frames, -1)], 1).float()


def run_scans(model: HeadNeckModel, truth: Truth, seed: int) -> dict:
    out = {}
    clouds_mm = [10 * c for c in scan_sequence(truth.clean.numpy(), model.rig.faces, seed, ScanConfig(
        points=25000, holes=3, hole_diameter_cm=3.0, noise_cm=NOISE_CM, stray_share=0.03))]
    clouds = [c / 10 for c in clouds_mm]   # motion.fit converts units=mm to cm before the solver
    result, wall, cpu = timed(lambda: fit_scans(model, clouds))
    out["fit"] = scores(model, truth, result, wall, cpu)
    result, wall, cpu = timed(lambda: fit_scans(model, clouds, FitSettings(neck_prior="none")))
    out["fit_no_neck_prior"] = scores(model, truth, result, wall, cpu)
    result, wall, cpu = timed(lambda: fit_scans(model, clouds, FitSettings(**BASELINE)))
    out["per_frame"] = scores(model, truth, result, wall, cpu)
    tris = triangulate(model.rig.faces)
    visible = torch.tensor(np.stack([vertex_normals(frame, tris)[:, 2] > 0 for frame in truth.clean.numpy()]))
    result, wall, cpu = timed(lambda: fit_weighted_meshes(model, truth.noisy, visible.float(), FitSettings()))
    out["bound"] = scores(model, truth, result, wall, cpu)
    return out


def run_person(model: HeadNeckModel, truth_model: HeadNeckModel, truth: Truth) -> dict:
    out = {}
    noisy = truth.noisy.numpy()
    result, wall, cpu = timed(lambda: fit_meshes(model, noisy, FitSettings(fit_shape=True)))
    out["fit"] = scores(model, truth, result, wall, cpu, truth_model)
    result, wall, cpu = timed(lambda: fit_meshes(model, noisy))
    out["without_shape"] = scores(model, truth, result, wall, cpu, truth_model)
    result, wall, cpu = timed(lambda: fit_meshes(model, noisy, FitSettings(**BASELINE)))
    out["per_frame"] = scores(model, truth, result, wall, cpu, truth_model)
    result, wall, cpu = timed(lambda: fit_meshes(truth_model, noisy))
    out["bound"] = scores(truth_model, truth, result, wall, cpu)
    return out


def mean_scores(runs: list[dict]) -> dict:
    out = {}
    for method in runs[0]:
        keys = [k for k, v in runs[0][method].items() if isinstance(v, float)]
        out[method] = {k: float(np.mean([r[method][k] for r in runs])) for k in keys}
        out[method]["joints_per_level_deg"] = np.mean([r[method]["joints_per_level_deg"] for r in runs], 0).round(
            3).tolist()
        out[method]["uncertainty_deg"] = np.mean([r[method]["uncertainty_deg"] for r in runs], 0).round(3).tolist()
    return out


def main(argv=None) -> dict:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rig", default="builtin")
    parser.add_argument("--regimes", default="meshes,scans,person")
    parser.add_argument("--sequences", type=int, default=2)
    parser.add_argument("--seconds", type=float, default=3.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", default=None)
    args = parser.parse_args(argv)
    model = HeadNeckModel.from_config(args.rig)
    prior = sample_sequences(args.sequences, args.seed, PriorConfig(seconds=args.seconds))
    results: dict = {"rig": args.rig, "sequences": args.sequences, "seconds": args.seconds, "seed": args.seed,
                     "threads": torch.get_num_threads()}
    for regime in args.regimes.split(","):
        runs = []
        for i in range(args.sequences):
            rng = np.random.default_rng([args.seed, i, len(regime)])
            if regime == "person":
                truth_model = HeadNeckModel(reshaped_person(model.rig, seed=args.seed * 100 + i))
                truth = make_truth(truth_model, prior.theta[i], prior.fps, rng, facing_scanner=False)
                runs.append(run_person(model, truth_model, truth))
            elif regime == "scans":
                truth = make_truth(model, prior.theta[i], prior.fps, rng, facing_scanner=True)
                runs.append(run_scans(model, truth, seed=args.seed * 100 + i))
            else:
                truth = make_truth(model, prior.theta[i], prior.fps, rng, facing_scanner=False)
                runs.append(run_meshes(model, truth))
            print(regime, i, json.dumps({m: {k: round(v, 4) for k, v in s.items() if isinstance(v, float)}
                                         for m, s in runs[-1].items()}), flush=True)
        results[regime] = mean_scores(runs)
        for method, s in results[regime].items():
            print(f"{regime:7s} {method:14s} joints {s['joints_deg']:.3f} deg  head {s['head_deg']:.3f} deg  "
                  f"tau {s['tau_rmse']:.5f}  vertices {s['vertices_mm']:.3f} mm  "
                  f"{s['fps_wall']:.2f} frames/s ({s['fps_cpu']:.2f} per CPU)  levels {s['joints_per_level_deg']}",
                  flush=True)
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1))
    return results


if __name__ == "__main__":
    main()
