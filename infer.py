"""Inference on an expression capture: larynx, cervical spine, swallows and meshes.

    python infer.py expressions=take.csv checkpoint=runs/larynx_transformer/<run>/checkpoints/last.pt out=tau.csv
    python infer.py expressions=take.csv checkpoint=... head2neck=runs/head2neck/<run>/checkpoints/last.pt \
        theta_out=theta.npy swallow_template=template.csv swallow_at=[2.0,7.5] meshes=frames/ [rig=hack_rig.npz]

Reads an expression recording (any format ``data.expressions.read_expressions`` reads: Live Link
Face, ARKit or HACK-named CSV, header-less CSV or ``.npy`` with ``fps=``) and resamples it to one
frame rate (the larynx model's, else ``out_fps``, else the recording's).  Then, each optional:

- tau: the expression -> larynx transformer streamed over psi (``checkpoint``, with ``eta`` if the
  model takes it); without one the larynx rests (tau = 0);
- swallows: a swallow template (``python -m motion.swallow``) inserted at ``swallow_at`` seconds,
  blended as ``swallow_playback`` says (``motion.swallow.insert_swallows``);
- theta: the recording's head rotation (``HeadYaw, HeadPitch, HeadRoll``; conventions and options in
  ``motion/head2neck.py``) through the head -> cervical spine model (``head2neck``); without one, or
  without recorded head rotation, the neck rests (theta = 0);
- meshes: the rig posed with (theta, psi, tau, eta) per frame, one PLY or OBJ per frame in ``meshes``.

Outputs: the tau track ``out`` (CSV ``frame,time,tau,fps`` on the recording's clock, or ``.npy``),
theta ``theta_out`` (``.npy`` [T,8,3], bone frames of the rig), meshes; all written atomically.
tau is in UV units of the larynx map (+ = up the neck).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig
from tqdm import tqdm

from data.cli import config_dataclass, run_cli
from data.expressions import ExpressionTrack, read_expressions
from data.cli import as_list
from data.errors import InputError
from data.files import fresh_output_folder, save_npy
from data.tau_track import TauTrack, write_tau_track
from data.mesh_io import write_obj, write_ply
from models.checkpoint import load_model
from models.head2neck import predict_theta
from models.larynx_transformer import predict_tau
from models.rig import HeadNeckModel
from motion.head2neck import head_rotations_from_ypr, load_head2neck, recentered
from motion.swallow import SwallowConfig, insert_swallows, read_template

MESH_FORMATS = ("ply", "obj")
MESH_FILES = tuple(f"frame_*.{suffix}" for suffix in MESH_FORMATS)    # what write_meshes writes


@dataclass
class Animation:
    """Per-frame rig inputs at ``fps``: time [T] s, psi [T,55], tau [T], theta [T,8,3] (bone frames)."""

    time: np.ndarray
    fps: float
    psi: np.ndarray
    tau: np.ndarray
    theta: np.ndarray


def predict_neck(model, rig: HeadNeckModel, head_ypr: np.ndarray, units: str = "rad",
                 signs: tuple[float, float, float] = (1.0, 1.0, 1.0), recenter: bool = False,
                 label: str = "head rotation") -> np.ndarray:
    """Bone-frame theta [T,8,3] for recorded head yaw/pitch/roll [T,3] through a head2neck model."""
    head = head_rotations_from_ypr(head_ypr, units, signs, label)
    return predict_theta(model, rig, recentered(head) if recenter else head).numpy()


def animate(cfg: DictConfig, expressions: ExpressionTrack, rig: HeadNeckModel, neck_model=None) -> Animation:
    """The per-frame rig inputs ``cfg`` asks for (see the module docstring), at one frame rate;
    ``neck_model`` a head2neck model for ``rig``."""
    larynx_model = load_model(cfg.checkpoint, task="larynx_transformer")[0] if cfg.checkpoint else None
    fps = larynx_model.fps if larynx_model is not None else float(cfg.out_fps or expressions.fps)
    resampled = expressions.resampled(fps)
    if larynx_model is not None:
        tau = predict_tau(larynx_model, resampled.psi, None if cfg.subject is None else str(cfg.subject),
                          float(cfg.eta))
    else:
        tau = np.zeros(len(resampled))
    if cfg.swallow_template:
        template = read_template(cfg.swallow_template)
        playback = config_dataclass(SwallowConfig, cfg.swallow_playback, "swallow_playback (configs/infer.yaml)")
        try:
            tau = insert_swallows(tau, resampled.time, template, as_list(cfg.swallow_at),
                                  as_list(cfg.swallow_duration_scale), as_list(cfg.swallow_amplitude_scale), playback)
        except ValueError as e:  # an onset outside the take, scales that do not match the onsets
            raise InputError(f"swallow_at={as_list(cfg.swallow_at)} in {expressions.source}: {e}") from None
    theta = np.zeros((len(resampled), rig.num_joints, 3), dtype=np.float32)
    if neck_model is not None:
        if resampled.head_ypr is None:
            print(f"{expressions.source}: no head rotation recorded; the neck rests (theta = 0)")
        else:
            signs = (float(cfg.yaw_sign), float(cfg.pitch_sign), float(cfg.roll_sign))
            theta = predict_neck(neck_model, rig, resampled.head_ypr, cfg.head_units, signs, bool(cfg.recenter),
                                 f"{expressions.source} (HeadYaw, HeadPitch, HeadRoll)")
    return Animation(resampled.time, fps, resampled.psi, np.asarray(tau, dtype=np.float64), theta)


@torch.no_grad()
def write_meshes(folder: str | Path, rig: HeadNeckModel, animation: Animation, eta: float = 1.0,
                 mesh_format: str = "ply", batch: int = 64) -> list[Path]:
    """Pose the rig for every frame and write ``frame_00000.<mesh_format>`` ... into ``folder``."""
    if mesh_format not in MESH_FORMATS:
        raise InputError(f"mesh_format={mesh_format}: expected one of {', '.join(MESH_FORMATS)}")
    folder = fresh_output_folder(folder, MESH_FILES, "meshes")
    faces = rig.faces.numpy()
    paths = []
    count = len(animation.time)
    with tqdm(total=count, desc="meshes", unit="frame", disable=count < 64) as progress:
        for start in range(0, count, batch):
            stop = min(start + batch, count)
            vertices = rig(torch.as_tensor(animation.theta[start:stop], dtype=torch.float32),
                           torch.as_tensor(animation.psi[start:stop], dtype=torch.float32),
                           torch.as_tensor(animation.tau[start:stop], dtype=torch.float32),
                           torch.full((stop - start,), float(eta))).numpy()
            for offset, frame in enumerate(vertices):
                path = folder / f"frame_{start + offset:05d}.{mesh_format}"
                if mesh_format == "ply":
                    write_ply(path, frame, faces)
                else:
                    write_obj(path, frame, faces, rig.rig.uv_coords, rig.rig.faces_uv)
                paths.append(path)
            progress.update(stop - start)
    return paths


def check_request(cfg: DictConfig) -> None:
    """Settings that can be wrong before anything is read or written: InputError naming the keys."""
    if not (cfg.out or cfg.theta_out or cfg.meshes):
        raise InputError("nothing to write: give out=tau.csv, theta_out=theta.npy and/or meshes=folder/")
    if bool(cfg.swallow_template) != bool(as_list(cfg.swallow_at)):
        raise InputError("swallows need both swallow_template=template.csv and swallow_at=[t1,...] (seconds); "
                         f"got swallow_template={cfg.swallow_template}, swallow_at={as_list(cfg.swallow_at)}")
    if cfg.meshes:
        if cfg.mesh_format not in MESH_FORMATS:
            raise InputError(f"mesh_format={cfg.mesh_format}: expected one of {', '.join(MESH_FORMATS)}")
        fresh_output_folder(cfg.meshes, MESH_FILES, "meshes")


def run(cfg: DictConfig) -> Animation:
    check_request(cfg)
    expressions = read_expressions(cfg.expressions, fps=cfg.fps, timecode_fps=cfg.timecode_fps)
    if expressions.missing:
        print(f"{cfg.expressions}: no column for {', '.join(expressions.missing)} (left at 0)")
    if cfg.head2neck:  # the rig it was trained with, unless rig= says otherwise
        neck_model, rig = load_head2neck(cfg.head2neck, cfg.rig)
    else:
        neck_model, rig = None, HeadNeckModel.from_config(cfg.rig)
    animation = animate(cfg, expressions, rig, neck_model)
    if cfg.out:
        write_tau_track(cfg.out, TauTrack(animation.tau, animation.time, animation.fps, str(cfg.expressions)))
        print(f"{cfg.out}: tau for {len(animation.tau)} frames at {animation.fps:g} fps "
              f"({animation.time[-1] - animation.time[0]:.2f} s of {cfg.expressions})")
    if cfg.theta_out:
        save_npy(cfg.theta_out, animation.theta.astype(np.float32))
        print(f"{cfg.theta_out}: theta {list(animation.theta.shape)}")
    if cfg.meshes:
        paths = write_meshes(cfg.meshes, rig, animation, float(cfg.eta), str(cfg.mesh_format))
        print(f"{cfg.meshes}: {len(paths)} {cfg.mesh_format.upper()} meshes ({rig.num_vertices} vertices each)")
    return animation


if __name__ == "__main__":
    run_cli("infer", run)
