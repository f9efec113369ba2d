"""A synthetic capture for ``python -m motion.fit``, and the fit's score against its truth.

    python benchmarks/fit_app_check.py write --out capture/ [--kind meshes|scans] [--frames 10] [--rig hack_rig.npz]
        [--person]   # another person: data.fit_captures.reshaped_person (fit it with fit_shape=true)
    python -m motion.fit input=capture/ kind=scans units=mm [rig=hack_rig.npz] out_dir=fit/
    python benchmarks/fit_app_check.py score --out capture/ --fit fit/
    python benchmarks/fit_app_check.py roundtrip --out capture/ --fit fit/   # fit with export=[glb]; needs Blender

The generator is not the benchmark's (``data.fit_captures`` / ``bench_fit.py``: the prior's motions, a small
sway, scans sampled on triangles from a fixed view): every neck joint nods, turns and tilts by sines (up to
11 degrees a joint), the placement turns by about 50 degrees and sits 1.5 m from the origin, vertices in mm
with 1 mm of Gaussian noise per axis.  Scans (``--kind scans``) are the posed vertices on the face's side
of the head (half of them), with 1 mm noise and 3 % stray points in a 30 cm box about the head.  The truth
goes beside the capture (``<out>_truth.npz``).  ``score`` prints the joints' angle error (c6c7..oc1, mean
over frames), the world head orientation's error, tau's RMSE, the vertex RMS of the fitted mesh (placed in
the capture, the fitted shape included) against the clean capture, and what the fit reports.  ``roundtrip``
(issue 55's bar): the fit's ``anim.glb`` re-imported by Blender's glTF importer and posed at every frame, its
largest distance (cm) from the fitted mesh (the rig posed on the fitted shape) in the rig's frame.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from base.rotations import axis_angle_to_matrix  # noqa: E402
from data.mesh_io import write_ply  # noqa: E402
from data.params import load_params  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402
from scene.characters import person_rig, resolve_rig  # noqa: E402
from scene.gltf import METRES_PER_CM, split_uv_seams  # noqa: E402
from tests.blender_sampling import blender_vertices  # noqa: E402


def capture_sequence(rig: HeadNeckModel, frames: int, noise_mm: float = 1.0, seed: int = 0) -> dict:
    """Vertices [T,V,3] in mm in the capture's frame (``vertices_mm``) and the truth: theta [T,J,3] (bone
    frames), tau [T], psi [T,E], the world head orientation ``head_world`` [T,3,3]."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 30.0
    anatomical = np.zeros((frames, rig.num_joints, 3))
    anatomical[:, 1:, 0] = (0.05 + 0.15 * np.sin(2 * np.pi * 1.5 * t))[:, None] * np.linspace(0.5, 1.0, 7)
    anatomical[:, 1:, 1] = (0.1 * np.cos(2 * np.pi * 1.1 * t + 0.4))[:, None]
    anatomical[:, 1:, 2] = (0.04 * np.sin(2 * np.pi * 0.9 * t))[:, None]
    theta = rig.from_anatomical(torch.tensor(anatomical, dtype=torch.float32))
    psi = np.zeros((frames, rig.num_expressions), np.float32)
    psi[:, 2], psi[:, 9] = 0.5 + 0.3 * np.sin(4 * t), 0.3
    tau = (0.03 * np.sin(2 * np.pi * 1.2 * t)).astype(np.float32)
    eta = np.full(frames, 1.0, np.float32)
    sway = np.stack([0.3 + 0.05 * np.sin(t), -0.8 + 0.1 * t, 0.2 * np.cos(t)], axis=1)
    rotation = axis_angle_to_matrix(torch.tensor(sway)).numpy()
    translation = np.stack([12 + t, -40 + 0 * t, 150 + 2 * np.sin(t)], axis=1)        # cm
    with torch.no_grad():
        posed = rig(theta, torch.tensor(psi), torch.tensor(tau), torch.tensor(eta)).double().numpy()
        head = rig.head_rotation(theta).double().numpy()
    world = np.einsum("tab,tvb->tva", rotation, posed) + translation[:, None]
    return {"vertices_mm": 10 * world + rng.normal(0, noise_mm, world.shape), "theta": theta.numpy(), "tau": tau,
            "head_world": rotation @ head, "psi": psi, "clean_mm": 10 * world}


def scans(capture: dict, seed: int = 1, stray_share: float = 0.03) -> list[np.ndarray]:
    """The face's side of each frame's vertices (mm) plus stray points in a 30 cm box about the head."""
    rng = np.random.default_rng(seed)
    out = []
    for vertices, head in zip(capture["vertices_mm"], capture["head_world"]):
        centre = vertices.mean(0)
        front = vertices[(vertices - centre) @ (head @ np.array([0.0, 0.0, 1.0])) > 0]
        strays = centre + rng.uniform(-150, 150, (int(len(front) * stray_share), 3))
        out.append(np.concatenate([front, strays]))
    return out


def write(args) -> None:
    rig = HeadNeckModel.from_config(args.rig)
    if args.person:
        from data.fit_captures import reshaped_person

        rig = HeadNeckModel(reshaped_person(rig.rig, args.seed))
    capture = capture_sequence(rig, args.frames, seed=args.seed)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    frames = capture["vertices_mm"] if args.kind == "meshes" else scans(capture, args.seed + 1)
    for k, frame in enumerate(frames):
        write_ply(out / f"frame_{k}.ply", frame, rig.rig.faces if args.kind == "meshes" else np.zeros((0, 3), int))
    np.savez(f"{out}_truth.npz", theta=capture["theta"], tau=capture["tau"], head_world=capture["head_world"],
             clean_mm=capture["clean_mm"])
    print(f"wrote {len(frames)} {args.kind} to {out} (mm), the truth to {out}_truth.npz")


def score(args) -> None:
    params, truth = load_params(Path(args.fit) / "params.npz"), np.load(f"{Path(args.out)}_truth.npz")
    fitted = axis_angle_to_matrix(torch.as_tensor(params.theta[:, 1:], dtype=torch.float64)).numpy()
    true = axis_angle_to_matrix(torch.as_tensor(truth["theta"][:, 1:], dtype=torch.float64)).numpy()
    joints = np.degrees(np.arccos(np.clip((np.trace(np.swapaxes(fitted, -1, -2) @ true, axis1=-2, axis2=-1) - 1) / 2,
                                          -1, 1)))
    head = params.root_rotation.astype(np.float64) @ params.head_rotation
    cos = (np.trace(np.swapaxes(head, 1, 2) @ truth["head_world"], axis1=1, axis2=2) - 1) / 2
    report = json.loads((Path(args.fit) / "report.json").read_text())
    posed = fitted_mesh(params, Path(args.fit), args.rig)
    placed = np.einsum("tab,tvb->tva", params.root_rotation.astype(np.float64), posed)
    placed = placed + params.root_translation[:, None]
    vertex_rms = np.sqrt(np.mean(np.sum((10 * placed - truth["clean_mm"]) ** 2, axis=-1))) \
        if "clean_mm" in truth.files else np.nan   # captures written before the truth held it
    print(f"joints c6c7..oc1 (deg, mean over frames): {np.round(joints.mean(0), 2).tolist()}, mean {joints.mean():.3f}")
    print(f"head (deg): mean {np.degrees(np.arccos(np.clip(cos, -1, 1))).mean():.3f}, "
          f"max {np.degrees(np.arccos(np.clip(cos, -1, 1))).max():.3f}")
    print(f"vertices to the clean capture: RMS {vertex_rms:.3f} mm (shape offset "
          f"{'fitted' if params.shape_offset is not None else 'none'})")
    print(f"tau RMSE {np.sqrt(np.mean((params.tau - truth['tau']) ** 2)):.5f}; residual {report['fit_rms_mm']}; "
          f"{report['frames_per_s']} frames/s; uncertainty {report['joint_uncertainty_deg']}")


def fitted_mesh(params, fit: Path, rig: str | None) -> np.ndarray:
    """The fit's mesh [T,V,3] cm in the rig's frame: the rig on the fitted shape, posed by the fit."""
    model = person_rig(resolve_rig(params, fit / "params.npz", rig), params)
    with torch.no_grad():
        return model(torch.as_tensor(params.theta), torch.as_tensor(params.psi), torch.as_tensor(params.tau),
                     torch.as_tensor(params.eta)).double().numpy()


def roundtrip(args) -> None:
    fit = Path(args.fit)
    params = load_params(fit / "params.npz")
    posed = fitted_mesh(params, fit, args.rig)
    order = split_uv_seams(resolve_rig(params, fit / "params.npz", args.rig)).rig_index
    frames = np.arange(len(params))
    blender = blender_vertices(fit / "anim.glb", params.fps, frames)["vertices"]   # metres, Blender's z up
    in_rig_frame = np.stack([blender[..., 0], blender[..., 2], -blender[..., 1]], axis=-1) / METRES_PER_CM
    error = np.linalg.norm(in_rig_frame - posed[:, order], axis=-1)
    offset = 0.0 if params.shape_offset is None else float(np.linalg.norm(params.shape_offset, axis=-1).max())
    print(f"round trip fit -> params.npz -> anim.glb -> Blender, {len(frames)} frames, {posed.shape[1]} vertices: "
          f"max {error.max():.5f} cm (frame {int(error.max(1).argmax())}), mean {error.mean():.6f} cm; "
          f"shape offset up to {offset:.3f} cm")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("mode", choices=("write", "score", "roundtrip"))
    parser.add_argument("--out", required=True, help="the capture folder (its truth beside it)")
    parser.add_argument("--fit", help="score: the fit's out_dir")
    parser.add_argument("--kind", choices=("meshes", "scans"), default="meshes")
    parser.add_argument("--frames", type=int, default=10)
    parser.add_argument("--rig", default=None)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--person", action="store_true", help="write: another person's shape")
    args = parser.parse_args()
    {"write": write, "score": score, "roundtrip": roundtrip}[args.mode](args)


if __name__ == "__main__":
    main()
