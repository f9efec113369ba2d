"""Inference: hand it a facial capture, get the neck that goes with it.

    python infer.py                                    # the built-in demo take, shipped models
    python infer.py expressions=take.csv [out_dir=out/]
    python infer.py expressions=takes/ workers=2       # every take in a folder, one subfolder each
    python infer.py expressions=take.csv checkpoint=runs/larynx_transformer/<run>/checkpoints/last.pt \\
        head2neck=none swallow_at=[2.0,7.5] meshes=true export=[glb,mp4] [rig=hack_rig.npz]

Reads an expression recording (``data.expressions.read_expressions``: Live Link Face, ARKit or
HACK-named CSV, header-less 55-column CSV, or ``.npy`` with ``fps=``), resamples it to one frame rate
(the larynx model's, else ``out_fps``, else the recording's) and computes, per frame:

- tau: the expression -> larynx transformer streamed over psi (``checkpoint``: ``default`` = the shipped
  model, ``none`` = the larynx rests, or a train.py checkpoint);
- swallows: a swallow template (``swallow_template``: ``default`` = the shipped one, or a template
  CSV from ``python -m motion.swallow``) inserted at ``swallow_at`` seconds (the demo take: at 6.2 s),
  blended as ``swallow_playback`` says;
- theta: the recording's head rotation (``HeadYaw, HeadPitch, HeadRoll``; conventions and options in
  ``motion/head2neck/__init__.py``) through the head -> cervical spine model (``head2neck``: ``default``,
  ``none`` or a checkpoint) in the bone frames of the rig; without recorded head rotation the neck rests.

Everything goes into one folder, ``out_dir`` (default ``runs/infer/<time>/``), written whole or not at
all (a staging folder renamed into place): ``params.npz`` (``data.params``: the file ``motion.retarget``
and the exporters read), ``params.csv`` (a row per frame), ``plot.png`` (tau and eta with the swallows,
the joints' anatomical angles), ``meshes/frame_00000.ply ...`` with ``meshes=true``, ``anim.glb``
(``scene.gltf``: Blender, Unity, three.js) and ``preview.mp4`` (``scene.preview``) with
``export=[glb,mp4]``.  A folder of takes gives one subfolder per take, a summary table (``summary.csv``),
and goes on past a take that fails, naming its reason.
"""
from __future__ import annotations

import json
import os
import shutil
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from datetime import datetime
from multiprocessing import get_context
from pathlib import Path
from typing import Any

import numpy as np
import torch
from omegaconf import OmegaConf

from base.cli import as_list, register_config, run_cli, to_dataclass
from base.errors import InputError
from base.files import write_csv
from base.plots import figure, save_figure
from base.progress import progress_bar
from data.demo_take import DEMO_SOURCE, SWALLOW_ONSET, demo_take
from data.expressions import EXPRESSION_NAMES, ExpressionTrack, arkit_name, read_expressions
from data.mesh_io import write_obj, write_ply
from data.params import AnimationParams, load_params, rig_checksum, save_params
from models.checkpoint import load_model
from models.head2neck import predict_theta
from models.larynx import predict_tau
from models.pretrained import default_checkpoint, pretrained_path, read_manifest
from models.rig import HeadNeckModel
from motion.head2neck import head_rotations_from_ypr, load_head2neck, recentered
from motion.retarget import default_gains, retarget_params
from motion.swallow import PlaybackConfig, insert_swallows, read_template
from scene.characters import GIRAFFE_TAG, load_character
from scene.gltf import export_glb
from scene.preview import Panel, anatomical_degrees, write_preview

MESH_FORMATS = ("ply", "obj")
EXPORTS = ("glb", "mp4")
TAKE_SUFFIXES = (".csv", ".npy")
# Expressions no ARKit capture has (ICT's cheekRaiser_L/R): their absence is a note, not an error.
NEVER_IN_ARKIT = tuple(name for name in EXPRESSION_NAMES if arkit_name(name) is None)


@dataclass
class InferConfig:
    """``python infer.py``: settings (see the module docstring)."""

    expressions: str | None = None  # a recording (.csv/.npy), a folder of them, or null for the demo take
    out_dir: str | None = None      # null: runs/infer/<time>/
    fps: float | None = None        # frame rate of header-less or .npy expressions (others carry their own)
    timecode_fps: float | None = None  # Live Link Face timecode rate, needed for takes under a second
    out_fps: float | None = None    # output rate without a larynx model; null = the recording's
    allow_missing: bool = False        # run a capture that lacks some ARKit expression columns (left at 0)
    # expressions -> tau
    checkpoint: str = "default"        # larynx model: default (shipped) | none (the larynx rests) | a checkpoint
    subject: str | None = None         # a training subject's style; null = the average style
    eta: float = 1.0                   # larynx size
    # swallows
    swallow_template: str = "default"  # default (shipped) | a template CSV from python -m motion.swallow
    swallow_at: list[float] = field(default_factory=list)  # onset times (s); the demo take swallows at 6.2 s
    swallow_duration_scale: Any = 1.0  # one value or one per onset
    swallow_amplitude_scale: Any = 1.0
    swallow_playback: PlaybackConfig = field(default_factory=PlaybackConfig)
    # head rotation -> cervical theta (conventions in motion/head2neck/__init__.py)
    head2neck: str = "default"         # default (shipped) | none (the neck rests) | a checkpoint
    head_units: str = "rad"            # rad | deg | halfturn
    yaw_sign: float = 1.0
    pitch_sign: float = 1.0
    roll_sign: float = 1.0
    recenter: bool = False
    # rig and outputs
    rig: str | None = None             # rig file from python -m data.assets; null = the built-in rig
    character: str = "human"           # human | giraffe (built from the rig) | a character file (.npz)
    meshes: bool = False               # one mesh per frame in meshes/
    mesh_format: str = "ply"           # ply | obj
    export: list[str] = field(default_factory=list)  # glb, mp4
    plot: bool = True
    workers: int = 1                   # takes of a folder run in this many processes
    threads: int = 1                   # torch threads per process (per-frame decoding runs on one)

    def __post_init__(self) -> None:
        if self.mesh_format not in MESH_FORMATS:
            raise ValueError(f"mesh_format={self.mesh_format}: expected one of {', '.join(MESH_FORMATS)}")
        unknown = [e for e in self.export if e not in EXPORTS]
        if unknown:
            raise ValueError(f"export={unknown}: expected some of {', '.join(EXPORTS)}")
        if self.workers < 1:
            raise ValueError(f"workers={self.workers}: expected at least 1")
        if self.swallow_template != "default" and not self.swallow_at:
            raise ValueError(f"swallow_template={self.swallow_template} needs swallow_at=[t1,...] (seconds)")


register_config("infer_schema", InferConfig)


# ----------------------------------------------------------------------------- models


@dataclass
class Models:
    """What drives the neck: the larynx model, the neck model and the rig (theta is in its bone frames)."""

    rig: HeadNeckModel
    rig_name: str
    larynx: torch.nn.Module | None = None
    neck: torch.nn.Module | None = None
    producers: dict = field(default_factory=dict)
    character: HeadNeckModel | None = None  # the character the motion is retargeted onto (None: the rig's own)


def _choice(value: str | None) -> str:
    return "none" if value is None or str(value).lower() in ("none", "null", "") else str(value)


def load_models(cfg: InferConfig, announce=print) -> Models:
    """The larynx and neck models ``cfg`` names (``default`` = shipped, ``none`` = at rest) and the rig."""
    producers = {"tool": "infer.py"}
    larynx = None
    choice = _choice(cfg.checkpoint)
    if choice == "default":
        if "larynx_transformer" in read_manifest():
            path = default_checkpoint("larynx_transformer")
            larynx = load_model(path, task="larynx_transformer")[0]
            announce(f"larynx: the shipped model {path.name} (checkpoint=<file> for another, checkpoint=none for none)")
            producers["larynx"] = f"shipped:{path.name}"
        else:
            announce("larynx: no shipped model in models/pretrained; the larynx rests (give checkpoint=<file>)")
    elif choice != "none":
        larynx = load_model(choice, task="larynx_transformer")[0]
        producers["larynx"] = choice
    neck_path = None
    choice = _choice(cfg.head2neck)
    if choice == "default":
        if "head2neck" in read_manifest():
            neck_path = default_checkpoint("head2neck")
            announce(f"neck: the shipped model {neck_path.name} (head2neck=<file> for another, head2neck=none "
                     f"for none)")
            producers["head2neck"] = f"shipped:{neck_path.name}"
        else:
            announce("neck: no shipped model in models/pretrained; the neck rests (give head2neck=<file>)")
    elif choice != "none":
        neck_path = choice
        producers["head2neck"] = choice
    if neck_path is not None:
        neck, rig = load_head2neck(neck_path, cfg.rig)
    else:
        neck, rig = None, HeadNeckModel.from_config(cfg.rig)
    rig_name = "builtin" if cfg.rig in (None, "", "builtin") else str(Path(cfg.rig).resolve())
    character = None
    if cfg.character != "human":
        character = HeadNeckModel(load_character(cfg.character, rig.rig))
        announce(f"character: {cfg.character} ({character.num_vertices} vertices); the motion is retargeted onto it")
    return Models(rig, rig_name, larynx, neck, producers, character)


# ----------------------------------------------------------------------------- one take


def read_take(cfg: InferConfig, path: str | None) -> ExpressionTrack:
    """The recording at ``path`` (or the demo take), refusing one that lacks ARKit expression columns
    unless ``allow_missing``."""
    if path is None:
        return demo_take()
    track = read_expressions(path, fps=cfg.fps, timecode_fps=cfg.timecode_fps)
    lacking = [name for name in track.missing if name not in NEVER_IN_ARKIT]
    if lacking and not cfg.allow_missing:
        columns = sorted({arkit_name(name) or name for name in lacking})
        raise InputError(f"{path}: no column for {len(lacking)} of the {len(EXPRESSION_NAMES)} expressions "
                         f"({', '.join(columns[:8])}{', ...' if len(columns) > 8 else ''}); expected a full "
                         f"ARKit / HACK capture, or allow_missing=true to run with them at 0")
    return track


def head_theta(cfg: InferConfig, models: Models, track: ExpressionTrack, announce=print) -> np.ndarray:
    """Bone-frame theta [T,J,3] from the take's head rotation (zeros without a neck model or rotation)."""
    theta = np.zeros((len(track), models.rig.num_joints, 3), dtype=np.float32)
    if models.neck is None:
        return theta
    if track.head_ypr is None:
        announce(f"{track.source}: no head rotation recorded (HeadYaw/HeadPitch/HeadRoll absent or zero); "
                 f"the neck rests")
        return theta
    signs = (float(cfg.yaw_sign), float(cfg.pitch_sign), float(cfg.roll_sign))
    head = head_rotations_from_ypr(track.head_ypr, cfg.head_units, signs,
                                   f"{track.source} (HeadYaw, HeadPitch, HeadRoll)")
    return predict_theta(models.neck, models.rig, recentered(head) if cfg.recenter else head).numpy()


def animate(cfg: InferConfig, models: Models, track: ExpressionTrack, announce=print) -> tuple[AnimationParams, dict]:
    """The per-frame rig inputs for one take, and the seconds each stage took."""
    seconds = {}
    started = time.perf_counter()
    fps = models.larynx.fps if models.larynx is not None else float(cfg.out_fps or track.fps)
    uniform = track.resampled(fps)
    seconds["resample"] = time.perf_counter() - started
    started = time.perf_counter()
    if models.larynx is not None:
        tau = predict_tau(models.larynx, uniform.psi, cfg.subject, float(cfg.eta))
    else:
        tau = np.zeros(len(uniform))
    seconds["larynx"] = time.perf_counter() - started
    onsets = [float(t) for t in as_list(cfg.swallow_at)]
    if track.source == DEMO_SOURCE and not onsets:
        onsets = [SWALLOW_ONSET]
    if onsets:
        path = pretrained_path("swallow_template") if cfg.swallow_template == "default" else cfg.swallow_template
        template = read_template(path)
        playback = cfg.swallow_playback
        try:
            tau = insert_swallows(tau, uniform.time, template, onsets, as_list(cfg.swallow_duration_scale),
                                  as_list(cfg.swallow_amplitude_scale), playback)
        except ValueError as e:  # an onset outside the take, scales that do not match the onsets
            raise InputError(f"swallow_at={onsets} in {track.source}: {e}") from None
    started = time.perf_counter()
    theta = head_theta(cfg, models, uniform, announce)
    with torch.no_grad():
        head = models.rig.head_rotation(torch.as_tensor(theta)).numpy()
    seconds["head2neck"] = time.perf_counter() - started
    params = AnimationParams(
        time=uniform.time - uniform.time[0], fps=fps, psi=uniform.psi, tau=tau,
        eta=np.full(len(uniform), float(cfg.eta)), theta=theta, head_rotation=head,
        joint_names=models.rig.joint_names, expression_names=models.rig.expression_names,
        rig=models.rig_name, rig_checksum=rig_checksum(models.rig.rig),
        producers={**models.producers, "swallows": onsets, "source": str(track.source)})
    return params, seconds


def write_params_csv(path: Path, params: AnimationParams, rig: HeadNeckModel) -> None:
    """One row a frame: time, tau, eta, the 55 weights, and each joint's bone-frame axis-angle (rad)."""
    columns = {"frame": np.arange(len(params)), "time": params.time, "tau": params.tau, "eta": params.eta}
    columns.update({name: params.psi[:, k] for k, name in enumerate(params.expression_names)})
    for j, joint in enumerate(params.joint_names):
        for a, axis in enumerate("xyz"):
            columns[f"theta_{joint}_{axis}"] = params.theta[:, j, a]
    write_csv(path, columns, float_format="%.7g")


def plot_take(path: Path, params: AnimationParams, rig: HeadNeckModel) -> None:
    """tau and eta over time with the swallow onsets, and the joints' anatomical angles over time."""
    fig, axes = figure(nrows=4, figsize=(10, 9), sharex=True)
    axes[0].plot(params.time, params.tau, color="tab:blue", label="tau (UV units, + = up)")
    axes[0].set_ylabel("tau")
    twin = axes[0].twinx()
    twin.plot(params.time, params.eta, color="tab:gray", linestyle="--", label="eta")
    twin.set_ylabel("eta")
    for onset in params.producers.get("swallows", []):
        axes[0].axvline(onset, color="tab:red", alpha=0.5)
    axes[0].set_title(f"{params.producers.get('source', '')}: larynx (red: swallows)")
    degrees = anatomical_degrees(rig, params.theta)
    for a, label in enumerate(("flexion (+) / extension", "axial rotation (+ = left)", "lateral bend (+ = right)")):
        for j, joint in enumerate(params.joint_names):
            axes[a + 1].plot(params.time, degrees[:, j, a], label=joint)
        axes[a + 1].set_ylabel(f"{label}\n(deg)")
    axes[1].legend(ncol=8, fontsize=7, loc="upper right")
    axes[-1].set_xlabel("time (s)")
    save_figure(fig, path)


@torch.no_grad()
def write_meshes(folder: Path, rig: HeadNeckModel, params: AnimationParams, mesh_format: str = "ply",
                 batch: int = 64) -> int:
    """Pose the rig for every frame and write ``frame_00000.<mesh_format>`` ... into ``folder``."""
    folder.mkdir(parents=True, exist_ok=True)
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


def write_outputs(cfg: InferConfig, models: Models, params: AnimationParams, folder: Path, announce=print) -> dict:
    """Everything for one take into ``folder`` (``params`` drive the character when there is one); the
    seconds each output took."""
    rig = models.rig if models.character is None else models.character
    seconds = {}
    started = time.perf_counter()
    save_params(folder / "params.npz", params)
    write_params_csv(folder / "params.csv", params, rig)
    seconds["write"] = time.perf_counter() - started
    if cfg.plot:
        started = time.perf_counter()
        plot_take(folder / "plot.png", params, rig)
        seconds["plot"] = time.perf_counter() - started
    if cfg.meshes:
        started = time.perf_counter()
        write_meshes(folder / "meshes", rig, params, cfg.mesh_format)
        seconds["meshes"] = time.perf_counter() - started
    if "glb" in cfg.export:
        started = time.perf_counter()
        report = export_glb(params, rig, folder / "anim.glb", check=False,
                            source=str(params.producers["source"]))
        announce(report.summary())
        seconds["glb"] = time.perf_counter() - started
    if "mp4" in cfg.export:
        started = time.perf_counter()
        panels = [Panel.create(rig, params)]
        if models.character is not None:  # side by side: the capture's own rig, then the character
            panels.insert(0, Panel.create(models.rig, load_params(folder / "source_params.npz")))
        write_preview(folder / "preview.mp4", panels)
        seconds["mp4"] = time.perf_counter() - started
    return seconds


def staged_folder(out_dir: Path) -> Path:
    """A staging folder beside ``out_dir`` (renamed into place by :func:`commit_folder`)."""
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise InputError(f"out_dir={out_dir}: already exists and is not an empty folder; give a new one")
    out_dir.parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f".{out_dir.name}.", suffix=".partial", dir=out_dir.parent))


def commit_folder(staging: Path, out_dir: Path) -> None:
    """Rename the finished staging folder to ``out_dir`` with a normal folder's mode (mkdtemp makes 0700)."""
    if out_dir.is_dir():
        out_dir.rmdir()  # empty (checked by staged_folder)
    umask = os.umask(0)
    os.umask(umask)
    os.chmod(staging, 0o777 & ~umask)
    os.replace(staging, out_dir)


def run_take(cfg: InferConfig, models: Models, path: str | None, out_dir: Path, announce=print) -> dict:
    """Read, animate and write one take into ``out_dir`` (whole or not at all); a summary row."""
    started = time.perf_counter()
    track = read_take(cfg, path)
    read_seconds = time.perf_counter() - started
    if track.missing:
        announce(f"{track.source}: no column for {', '.join(track.missing)} (left at 0)")
    params, seconds = animate(cfg, models, track, announce)
    staging = staged_folder(out_dir)
    try:
        if models.character is not None:
            started = time.perf_counter()
            save_params(staging / "source_params.npz", params)
            label = str(cfg.character)
            if cfg.character == GIRAFFE_TAG:  # built on the fly: the file beside the params names it
                models.character.rig.save(staging / "character.npz")
                label = str((out_dir / "character.npz").resolve())
            params = retarget_params(params, models.rig, models.character, label, default_gains(models.character),
                                     source_name=str(track.source))
            seconds["retarget"] = time.perf_counter() - started
        seconds.update(write_outputs(cfg, models, params, staging, announce))
        commit_folder(staging, out_dir)
    finally:
        if staging.exists():
            shutil.rmtree(staging)
    seconds = {"read": read_seconds, **seconds}
    return {"take": str(track.source), "status": "ok", "frames": len(params), "fps": params.fps,
            "seconds": round(float(params.time[-1]), 3), "tau_range": float(np.ptp(params.tau)),
            "max_joint_deg": float(np.degrees(np.linalg.norm(params.theta, axis=-1)).max()),
            "out": str(out_dir), "stage_seconds": seconds, "reason": ""}


# ----------------------------------------------------------------------------- many takes


def takes_in(folder: Path) -> list[Path]:
    takes = sorted(p for p in folder.iterdir() if p.is_file() and p.suffix.lower() in TAKE_SUFFIXES)
    if not takes:
        raise InputError(f"expressions={folder}: a folder without .csv or .npy takes")
    return takes


_WORKER: dict = {}


def _init_worker(cfg_dict: dict) -> None:
    cfg = InferConfig(**{**cfg_dict, "swallow_playback": PlaybackConfig(**cfg_dict["swallow_playback"])})
    torch.set_num_threads(max(1, int(cfg.threads)))
    _WORKER["cfg"] = cfg
    _WORKER["models"] = load_models(cfg, announce=lambda message: None)


def _take_row(cfg: InferConfig, models: Models, take: Path, out_dir: Path, announce=print) -> dict:
    try:
        return run_take(cfg, models, str(take), out_dir, announce)
    except InputError as e:
        return {"take": str(take), "status": "failed", "reason": str(e), "out": ""}


def _worker_take(take: str, out_dir: str) -> dict:
    return _take_row(_WORKER["cfg"], _WORKER["models"], Path(take), Path(out_dir), announce=lambda message: None)


def run_folder(cfg: InferConfig, folder: Path, out_dir: Path) -> list[dict]:
    """Every take of ``folder`` into ``out_dir/<take>/``; failures reported, the others go on."""
    takes = takes_in(folder)
    if out_dir.exists() and (not out_dir.is_dir() or any(out_dir.iterdir())):
        raise InputError(f"out_dir={out_dir}: already exists and is not an empty folder; give a new one")
    targets = [out_dir / take.stem for take in takes]
    if len({t.name for t in targets}) < len(targets):
        targets = [out_dir / f"{take.stem}{take.suffix.replace('.', '_')}" for take in takes]
    rows = []
    progress = progress_bar(total=len(takes), desc="takes", unit="take")
    if cfg.workers > 1 and len(takes) > 1:
        cfg_dict = OmegaConf.to_container(OmegaConf.structured(cfg))
        with ProcessPoolExecutor(min(cfg.workers, len(takes)), mp_context=get_context("spawn"),
                                 initializer=_init_worker, initargs=(cfg_dict,)) as pool:
            futures = [pool.submit(_worker_take, str(take), str(target)) for take, target in zip(takes, targets)]
            for future in futures:
                rows.append(future.result())
                progress.update(1)
    else:
        models = load_models(cfg)
        for take, target in zip(takes, targets):
            rows.append(_take_row(cfg, models, take, target))
            progress.update(1)
    progress.close()
    if any(row["status"] == "ok" for row in rows):
        out_dir.mkdir(parents=True, exist_ok=True)
        write_csv(out_dir / "summary.csv", {
            "take": [r["take"] for r in rows], "status": [r["status"] for r in rows],
            "frames": [r.get("frames", 0) for r in rows], "seconds": [r.get("seconds", 0.0) for r in rows],
            "out": [r["out"] for r in rows], "reason": [r["reason"] for r in rows]})
    return rows


def print_summary(rows: list[dict]) -> None:
    width = max(len(Path(r["take"]).name) for r in rows)
    print(f"\n{'take':<{width}}  status  frames  seconds  result")
    for r in rows:
        detail = r["out"] if r["status"] == "ok" else r["reason"]
        print(f"{Path(r['take']).name:<{width}}  {r['status']:<6}  {r.get('frames', 0):>6}  "
              f"{r.get('seconds', 0.0):>7.2f}  {detail}")
    failed = sum(r["status"] != "ok" for r in rows)
    print(f"{len(rows) - failed} of {len(rows)} takes done" + (f", {failed} failed" if failed else ""))


def default_out_dir() -> Path:
    return Path("runs") / "infer" / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def run(cfg) -> list[dict]:
    config: InferConfig = to_dataclass(cfg, where="infer")
    out_dir = Path(config.out_dir) if config.out_dir else default_out_dir()
    source = Path(config.expressions) if config.expressions is not None else None
    if source is not None and source.is_dir():
        rows = run_folder(config, source, out_dir)
        print_summary(rows)
        if not any(r["status"] == "ok" for r in rows):
            raise InputError(f"expressions={source}: no take could be run (reasons above)")
        return rows
    if source is None:
        print("expressions: none given; running the built-in demo take (12 s: talking, a head turn, a nod, a tilt)")
    models = load_models(config)
    row = run_take(config, models, None if source is None else str(source), out_dir)
    stages = ", ".join(f"{k} {v:.2f} s" for k, v in row["stage_seconds"].items())
    print(f"{out_dir}: {row['frames']} frames at {row['fps']:g} fps ({stages})\n"
          f"  open {out_dir / 'plot.png'} (the tracks), params.npz / params.csv (per-frame parameters)"
          + (", meshes/" if config.meshes else ""))
    print(json.dumps({k: row[k] for k in ("frames", "fps", "tau_range", "max_joint_deg")}))
    return [row]


if __name__ == "__main__":
    run_cli("infer", run, doc=__doc__)
