"""The files of one take: params.npz / params.csv, the plot, per-frame meshes, anim.glb, preview.mp4,
viewer.html, anim.fbx and anim.usdc (.usda, .usdz)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from base.files import write_csv
from base.plots import figure, save_figure
from base.progress import progress_bar
from base.rotations import matrix_to_axis_angle
from base.stopwatch import StageSeconds
from data.mesh_io import write_obj, write_ply
from data.params import AnimationParams, save_params
from models.rig import HeadNeckModel
from motion.pipeline.config import InferConfig
from motion.pipeline.models import Models
from scene.characters import person_rig
from scene.fbx import export_fbx
from scene.gltf import build_glb, write_glb
from scene.preview import Panel, anatomical_degrees, write_preview
from scene.usd import export_usd
from scene.viewer import build_viewer


def write_params_csv(path: Path, params: AnimationParams) -> None:
    """One row a frame: time, tau, eta, (with audio: f0 in Hz, 0 = unvoiced, and tau_voice, the voice's share
    of tau; from a fit: fit_rms_mm, the placement's translation root_t{x,y,z} in cm and rotation root_r{x,y,z}
    as axis-angle radians), the 55 weights, and each joint's bone-frame axis-angle (rad)."""
    columns = {"frame": np.arange(len(params)), "time": params.time, "tau": params.tau, "eta": params.eta}
    for name in ("f0", "tau_voice", "fit_rms_mm"):
        if getattr(params, name) is not None:
            columns[name] = getattr(params, name)
    if params.root_rotation is not None:
        root = matrix_to_axis_angle(torch.as_tensor(params.root_rotation, dtype=torch.float64)).numpy()
        columns.update({f"root_t{axis}": params.root_translation[:, a] for a, axis in enumerate("xyz")})
        columns.update({f"root_r{axis}": root[:, a] for a, axis in enumerate("xyz")})
    columns.update({name: params.psi[:, k] for k, name in enumerate(params.expression_names)})
    for j, joint in enumerate(params.joint_names):
        for a, axis in enumerate("xyz"):
            columns[f"theta_{joint}_{axis}"] = params.theta[:, j, a]
    write_csv(path, columns, float_format="%.7g")


def plot_take(path: Path, params: AnimationParams, rig: HeadNeckModel) -> None:
    """tau and eta over time with the swallow onsets, the voice (F0 and its term) when there is one, and the
    joints' anatomical angles over time."""
    voice = params.f0 is not None
    fig, axes = figure(nrows=5 if voice else 4, figsize=(10, 11 if voice else 9), sharex=True)
    axes[0].plot(params.time, params.tau, color="tab:blue", label="tau (UV units, + = up)")
    axes[0].set_ylabel("tau")
    twin = axes[0].twinx()
    twin.plot(params.time, params.eta, color="tab:gray", linestyle="--", label="eta")
    twin.set_ylabel("eta")
    for onset in params.producers.get("swallows", []):
        axes[0].axvline(onset, color="tab:red", alpha=0.5)
    axes[0].set_title(f"{params.producers.get('source', '')}: larynx (red: swallows)")
    if voice:
        plot_voice(axes[1], params)
        axes = [axes[0], *axes[2:]]
    degrees = anatomical_degrees(rig, params.theta)
    for a, label in enumerate(("flexion (+) / extension", "axial rotation (+ = left)", "lateral bend (+ = right)")):
        for j, joint in enumerate(params.joint_names):
            axes[a + 1].plot(params.time, degrees[:, j, a], label=joint)
        axes[a + 1].set_ylabel(f"{label}\n(deg)")
    axes[1].legend(ncol=8, fontsize=7, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    save_figure(fig, path)


def plot_voice(axis, params: AnimationParams) -> None:
    """F0 (Hz, voiced frames only) and the voice term (tau units) on one panel."""
    axis.plot(params.time, np.where(params.f0 > 0, params.f0, np.nan), color="tab:purple", label="F0")
    axis.set_ylabel("F0 (Hz)")
    if params.tau_voice is not None:
        twin = axis.twinx()
        twin.plot(params.time, params.tau_voice, color="tab:orange", label="tau_voice")
        twin.set_ylabel("voice term (tau)")
    axis.set_title(f"voice: {params.producers.get('audio', '')} (purple: F0; orange: its share of tau)", fontsize=9)


@torch.no_grad()
def write_meshes(folder: Path, rig: HeadNeckModel, params: AnimationParams, mesh_format: str = "ply",
                 batch: int = 64) -> int:
    """Pose the rig for every frame and write ``frame_00000.<mesh_format>`` ... into ``folder`` (``rig``: the
    base rig; a fitted ``params.shape_offset`` is applied, ``scene.characters.person_rig``)."""
    folder.mkdir(parents=True, exist_ok=True)
    rig = person_rig(rig, params)
    faces = rig.faces.numpy()
    count = len(params)
    with progress_bar(total=count, desc="meshes", unit="frame", disable=count < 64) as progress:
        for start in range(0, count, batch):
            stop = min(start + batch, count)
            vertices = rig(torch.as_tensor(params.theta[start:stop]), torch.as_tensor(params.psi[start:stop]),
                           torch.as_tensor(params.tau[start:stop]), torch.as_tensor(params.eta[start:stop])).numpy()
            for offset, frame in enumerate(vertices):
                path = folder / f"frame_{start + offset:05d}.{mesh_format}"
                if mesh_format == "ply":
                    write_ply(path, frame, faces)
                else:
                    write_obj(path, frame, faces, rig.rig.uv_coords, rig.rig.faces_uv)
            progress.update(stop - start)
    return count


def write_outputs(cfg: InferConfig, models: Models, params: AnimationParams, folder: Path, announce=print,
                  out_dir: Path | None = None, source_params: AnimationParams | None = None,
                  seconds: StageSeconds | None = None) -> StageSeconds:
    """Everything for one take into ``folder`` (``params`` drive the character when there is one); the
    seconds each output took (added to ``seconds`` when given).  ``out_dir``: where ``folder`` (a staging
    folder) ends up, the name the reports give and the viewer's title.  ``source_params``: the take on the
    capture's own rig (``models.rig``) when ``params`` were retargeted onto a character, shown beside it in
    the preview and the viewer.  The GLB is built once, in memory, for anim.glb, the viewer and Blender."""
    out_dir = folder if out_dir is None else out_dir
    seconds = StageSeconds() if seconds is None else seconds

    def report_line(report) -> None:
        announce(report.summary().replace(str(folder), str(out_dir)))

    rig = models.rig if models.character is None else models.character
    source = str(params.producers["source"])
    with seconds.time("write"):
        save_params(folder / "params.npz", params)
        write_params_csv(folder / "params.csv", params)
    if cfg.plot:
        with seconds.time("plot"):
            plot_take(folder / "plot.png", params, rig)
    if cfg.meshes:
        with seconds.time("meshes"):
            write_meshes(folder / "meshes", rig, params, cfg.mesh_format)
    glb = None
    if {"glb", "html", "fbx"} & set(cfg.export):
        with seconds.time("glb"):  # morph normals only for the file and the page (Blender recomputes normals)
            glb = build_glb(params, rig, check=False, source=source,
                            morph_normals=bool({"glb", "html"} & set(cfg.export)))
            if "glb" in cfg.export:
                report_line(write_glb(glb, folder / "anim.glb"))
    if "mp4" in cfg.export:
        with seconds.time("mp4"):
            panels = [Panel.create(rig, params)]
            if source_params is not None:  # side by side: the capture's own rig, then the character
                panels.insert(0, Panel.create(models.rig, source_params))
            write_preview(folder / "preview.mp4", panels)
    if "html" in cfg.export:
        with seconds.time("html"):
            companion = None if source_params is None else (source_params, models.rig)
            report_line(build_viewer(params, rig, folder / "viewer.html", glb=glb.raw, title=out_dir.name,
                                     companion=companion))
    if "fbx" in cfg.export:
        with seconds.time("fbx"):
            take = Path(str(params.producers.get("source", "hackneck"))).stem
            report_line(export_fbx(params, rig, folder / "anim.fbx", cfg.fbx_units, glb=glb.raw, take=take))
    if "usd" in cfg.export:
        with seconds.time("usd"):
            report_line(export_usd(params, rig, folder / f"anim.{cfg.usd_format}", cfg.usd_units, source=source))
    return seconds
