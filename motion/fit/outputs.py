"""What ``motion.fit`` writes: the fit as :class:`data.params.AnimationParams`, ``plot.png`` (the residual over
time, tau and eta, the joints), ``report.json`` and the log's summary."""
from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from base.files import write_text
from base.plots import figure, save_figure
from data.params import AnimationParams, rig_checksum
from models.rig import HeadNeckModel
from scene.preview import anatomical_degrees

# A joint whose angle the data determine worse than this (the Gauss-Newton standard deviation, degrees) is
# named in the log as not pinned down by the skin: the bar for the mean joint error is 1 degree.
UNCERTAIN_DEG = 1.0
WORST_FRAMES = 5


def fit_params(result, model: HeadNeckModel, fps: float, rig_label: str, producers: dict) -> AnimationParams:
    """The ``FitResult`` as the params file infer.py writes: eta repeated per frame, head_rotation the
    rig-frame head pose of theta (the placement excluded), the fit's fields."""
    frames = len(result.theta)
    theta = np.asarray(result.theta, dtype=np.float32)
    with torch.no_grad():
        head = model.head_rotation(torch.as_tensor(theta)).numpy()
    return AnimationParams(
        time=np.arange(frames) / fps, fps=fps, psi=result.psi, tau=result.tau,
        eta=np.full(frames, float(result.eta), dtype=np.float32), theta=theta, head_rotation=head,
        joint_names=model.joint_names, expression_names=model.expression_names, rig=rig_label,
        rig_checksum=rig_checksum(model.rig), producers=producers, root_rotation=result.root_rotation,
        root_translation=result.root_translation, fit_rms_mm=result.fit_rms_mm, shape_offset=result.shape_offset)


def worst_frames(params: AnimationParams, names: list[str], count: int = WORST_FRAMES) -> list[dict]:
    """The ``count`` frames with the largest residual, largest first: frame, its input, rms in mm."""
    order = np.argsort(-params.fit_rms_mm, kind="stable")[:count]
    return [{"frame": int(k), "input": Path(names[k]).name, "rms_mm": round(float(params.fit_rms_mm[k]), 4)}
            for k in order]


def joint_uncertainty(result, model: HeadNeckModel) -> dict[str, float | None]:
    """Per joint the fit's standard deviation (degrees); None for the root (held: in the placement)."""
    values = np.asarray(result.joint_uncertainty_deg, dtype=np.float64)
    return {name: (None if not math.isfinite(v) else round(float(v), 4)) for name, v in zip(model.joint_names, values)}


def loose_joints(uncertainty: dict[str, float | None]) -> list[str]:
    """The joints the skin does not pin down (uncertainty above :data:`UNCERTAIN_DEG`)."""
    return [name for name, value in uncertainty.items() if value is not None and value > UNCERTAIN_DEG]


def plot_fit(path: Path, params: AnimationParams, model: HeadNeckModel, worst: list[dict]) -> None:
    """The residual per frame (worst frames marked), tau and eta, and the joints' anatomical angles."""
    fig, axes = figure(nrows=5, figsize=(10, 11), sharex=True)
    axes[0].plot(params.time, params.fit_rms_mm, color="tab:red")
    for row in worst:
        axes[0].axvline(params.time[row["frame"]], color="tab:red", alpha=0.25)
    axes[0].set_ylabel("residual RMS\n(mm)")
    axes[0].set_title(f"{params.producers.get('source', '')}: fit residual per frame (shaded: the worst frames)")
    axes[1].plot(params.time, params.tau, color="tab:blue")
    axes[1].set_ylabel("tau (UV units, + = up)")
    twin = axes[1].twinx()
    twin.plot(params.time, params.eta, color="tab:gray", linestyle="--")
    twin.set_ylabel("eta")
    degrees = anatomical_degrees(model, params.theta)
    for a, label in enumerate(("flexion (+) / extension", "axial rotation (+ = left)", "lateral bend (+ = right)")):
        for j, joint in enumerate(params.joint_names[1:], start=1):   # c7t1 is held (in the placement)
            axes[a + 2].plot(params.time, degrees[:, j, a], label=joint)
        axes[a + 2].set_ylabel(f"{label}\n(deg)")
    axes[2].legend(ncol=7, fontsize=7, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    save_figure(fig, path)


def fit_report(params: AnimationParams, result, model: HeadNeckModel, names: list[str], seconds: dict,
               settings: dict) -> dict:
    """report.json: frames, rates, the worst frames, per-joint uncertainty, shape, settings, the solver's own."""
    frames = len(params)
    uncertainty = joint_uncertainty(result, model)
    total = sum(seconds.values())
    report = {
        "frames": frames, "fps": params.fps,
        "frames_per_s": round(frames / total, 4) if total > 0 else None,
        "fit_frames_per_s": round(frames / seconds["fit"], 4) if seconds.get("fit") else None,
        "seconds": {k: round(v, 3) for k, v in seconds.items()},
        "fit_rms_mm": {"mean": float(np.mean(params.fit_rms_mm)), "median": float(np.median(params.fit_rms_mm)),
                       "max": float(np.max(params.fit_rms_mm))},
        "worst_frames": worst_frames(params, names),
        "joint_uncertainty_deg": uncertainty,
        "joints_not_pinned_down": loose_joints(uncertainty),
        "uncertain_above_deg": UNCERTAIN_DEG,
        "eta": float(result.eta),
        "settings": settings,
        "solver": result.report,
    }
    if params.shape_offset is not None:
        norms = np.linalg.norm(params.shape_offset, axis=1)
        report["shape_offset_cm"] = {"max": float(norms.max()), "rms": float(np.sqrt(np.mean(norms ** 2)))}
    return report


def write_report(path: Path, report: dict) -> None:
    write_text(path, json.dumps(report, indent=2, default=_jsonable) + "\n")


def _jsonable(value):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    return str(value)


def summary_lines(report: dict) -> list[str]:
    """The log's lines: rate, residual, worst frames, the joints the skin does not pin down."""
    worst = ", ".join(f"{w['frame']} ({w['input']}: {w['rms_mm']:.3g} mm)" for w in report["worst_frames"])
    uncertainty = ", ".join(f"{name} {'held' if v is None else f'{v:.2g}'}"
                            for name, v in report["joint_uncertainty_deg"].items())
    loose = report["joints_not_pinned_down"]
    lines = [f"fitted {report['frames']} frames: {report['frames_per_s']:.3g} frames/s end to end "
             f"(fit alone {report['fit_frames_per_s']:.3g} frames/s)",
             f"residual RMS: mean {report['fit_rms_mm']['mean']:.3g} mm, max {report['fit_rms_mm']['max']:.3g} mm; "
             f"worst frames: {worst}",
             f"joint uncertainty (deg, from the fit's Gauss-Newton Hessian): {uncertainty}"]
    if loose:
        lines.append(f"not pinned down by the skin (uncertainty > {UNCERTAIN_DEG:g} deg): {', '.join(loose)}; "
                     "their angles are the priors' more than the capture's")
    else:
        lines.append(f"every joint pinned down by the skin (uncertainty <= {UNCERTAIN_DEG:g} deg)")
    if "shape_offset_cm" in report:
        lines.append(f"shape offset: max {report['shape_offset_cm']['max']:.3g} cm, "
                     f"rms {report['shape_offset_cm']['rms']:.3g} cm")
    return lines
