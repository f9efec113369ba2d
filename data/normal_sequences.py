"""Synthetic normal-map sequences of the neck with the ground-truth larynx position, to test the tracker.

A sequence is rendered from the rig (``data.render``, default neck view)
with a known generating process, deterministic from its seed:

- tau: ``data.synthetic_tau.random_tau_trajectory`` (rest, swallows,
  speech-like 2-6 Hz motion, slow drift), UV units, + = up the neck.
- head motion: a smooth random rotation per axis of the joints' ANATOMICAL
  frames (``models.rig``: x flexion, y axial rotation, z lateral bending; a
  sum of three sinusoids below ``head_motion_hz``), scaled so its largest
  excursion is ``head_motion_deg`` (each axis draws a peak in [0.5, 1] x
  that), spread evenly over the 8 cervical joints (each joint turns 1/8 of
  it, so the head turns by about the whole).  The rig is posed with
  ``rig.from_anatomical(theta)`` (its bone frames need not be anatomical:
  the real HACK rig's oc1 bone points into the face).
- eta: one larynx size per sequence, uniform in [``eta_min``, ``eta_max``].
- image degradation, in order: optional Gaussian blur (``blur_px`` sigma,
  pixels), per-pixel Gaussian noise of std ``noise`` on each normal component,
  renormalised; optional 8-bit quantisation of the RGB encoding.
  Background pixels stay 0.

Ground truth: ``larynx_px [T,2]`` = (col, row) of the projection of the
rig's larynx point (``data.render.larynx_point``: the area-weighted centroid
of the posed surface where the larynx term exceeds 30 % of its maximum,
weighted by the excess), in the image convention of ``data.render`` (pixel
centres at integers, rows down).  The tracker's rig kernel is centred on the
same point at rest, so its reported position estimates exactly this.

CLI (hydra, ``configs/normal_sequences.yaml``)::

    python -m data.normal_sequences out=frames/ frames=300 seed=0 [format=png8|png16|exr|npy] [noise=0.05]

writes ``frame_00000.png ...`` (or ``normals.npy`` [T,H,W,3] float32 raw normals) and ``truth.csv``
(``frame,time,tau,x_px,y_px,eta,fps``, ``data.tau_track.write_tau_track``; x_px/y_px the ground truth above)
into ``out``.
"""
from __future__ import annotations

import time as _time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from data.cli import config_dataclass, run_cli
from data.errors import InputError
from data.files import fresh_output_folder, save_npy
from data.tau_track import TauTrack, write_tau_track
from data.normals import decode_normals, encode_normals, write_normal_image
from data.render import Camera, DEFAULT_CM_PER_PX, DEFAULT_SIZE, NeckRenderer, neck_camera
from data.synthetic_tau import random_tau_trajectory

SEQUENCE_FORMATS = ("png8", "png16", "exr", "npy")
SEQUENCE_FILES = ("frame_*", "normals.npy", "truth.csv")     # what write_sequence writes into its folder
CLI_KEYS = ("out", "format", "seed", "rig", "threads")       # configs/normal_sequences.yaml's keys besides SequenceConfig


@dataclass
class SequenceConfig:
    """Generator settings (mirrored by ``configs/normal_sequences.yaml``); angles in degrees, tau in UV units."""

    frames: int = 300
    fps: float = 30.0
    size: int = DEFAULT_SIZE              # square frames, pixels
    cm_per_px: float = DEFAULT_CM_PER_PX
    perspective: bool = False
    swallows_per_minute: float = 6.0
    speech: float = 0.008                 # std of the speech-like motion, tau units
    drift: float = 0.002                  # slow posture drift amplitude, tau units
    head_motion_deg: float = 3.0          # largest head excursion per axis
    head_motion_hz: float = 0.3           # highest frequency of the head motion
    eta_min: float = 0.8
    eta_max: float = 1.2
    noise: float = 0.05                   # std per normal component, before renormalising
    blur_px: float = 0.0                  # Gaussian blur sigma in pixels (0 = none)
    quantize_8bit: bool = False


@dataclass
class NormalSequence:
    """A rendered sequence and its truth.

    normals [T,H,W,3] float32 camera-space normals (0 on the background); mask [T,H,W] bool;
    larynx_px [T,2] (col, row) ground-truth larynx point; tau [T] UV units; theta [T,8,3] radians,
    axis-angle per joint in the ANATOMICAL joint frames (x flexion, y axial rotation, z lateral bending;
    the rig's bone-frame input is ``rig.from_anatomical(theta)``); eta larynx size; fps; camera the view.
    """

    normals: np.ndarray
    mask: np.ndarray
    larynx_px: np.ndarray
    tau: np.ndarray
    theta: np.ndarray
    eta: float
    fps: float
    camera: Camera

    @property
    def time(self) -> np.ndarray:
        return np.arange(len(self.tau)) / self.fps

    def __len__(self) -> int:
        return len(self.tau)


def head_motion(num_frames: int, fps: float, seed: int, amplitude_deg: float, max_hz: float,
                num_joints: int = 8) -> np.ndarray:
    """Smooth random neck pose theta [T,J,3] (radians, axis-angle in the joints' anatomical frames: x
    flexion, y axial rotation, z lateral bending): per axis a peak excursion in [0.5, 1] x
    ``amplitude_deg``, spread evenly over the joints."""
    rng = np.random.default_rng(seed)
    time = np.arange(num_frames) / fps
    angles = np.zeros((num_frames, 3))
    if amplitude_deg > 0:
        for axis in range(3):
            freqs = rng.uniform(0.05, max_hz, size=3)
            phases = rng.uniform(0, 2 * np.pi, size=3)
            weights = rng.uniform(0.5, 1.0, size=3)
            wave = (weights * np.sin(2 * np.pi * freqs * time[:, None] + phases)).sum(1)
            peak = np.abs(wave).max()
            angles[:, axis] = wave / (peak if peak > 0 else 1.0) * rng.uniform(0.5, 1.0) * np.radians(amplitude_deg)
    return np.repeat(angles[:, None, :] / num_joints, num_joints, axis=1)


def degrade(normals: np.ndarray, mask: np.ndarray, noise: float, blur_px: float, quantize_8bit: bool,
            rng: np.random.Generator) -> np.ndarray:
    """Blur, noise (renormalised) and 8-bit quantisation of normal maps [T,H,W,3] (background 0)."""
    out = normals.astype(np.float32, copy=True)
    fg = mask[..., None]
    if blur_px > 0:
        for t in range(len(out)):
            out[t] = cv2.GaussianBlur(out[t], (0, 0), blur_px)
    if noise > 0:
        out += rng.normal(0.0, noise, size=out.shape).astype(np.float32)
    if blur_px > 0 or noise > 0:
        out /= np.maximum(np.linalg.norm(out, axis=-1, keepdims=True), 1e-6)
    if quantize_8bit:
        out = decode_normals(np.rint(encode_normals(out) * 255.0) / 255.0)
    return np.where(fg, out, 0.0).astype(np.float32)


def make_sequence(rig, config: SequenceConfig, seed: int, chunk: int = 8) -> NormalSequence:
    """Render a synthetic sequence of ``config.frames`` frames (deterministic from ``seed``)."""
    rng = np.random.default_rng(seed)
    seeds = rng.integers(2**31, size=3)
    tau, _ = random_tau_trajectory(config.frames, config.fps, int(seeds[0]), config.swallows_per_minute,
                                   config.speech, config.drift)
    theta = head_motion(config.frames, config.fps, int(seeds[1]), config.head_motion_deg, config.head_motion_hz,
                        rig.num_joints)
    eta = float(rng.uniform(config.eta_min, config.eta_max))
    camera = neck_camera(rig, config.size, config.cm_per_px, config.perspective)
    renderer = NeckRenderer(rig, camera)
    theta_t = rig.from_anatomical(torch.tensor(theta, dtype=torch.float32))       # bone frames: the rig's input
    tau_t = torch.tensor(tau, dtype=torch.float32)
    render, pixels = renderer.render_with_truth(theta_t, tau=tau_t, eta=torch.full_like(tau_t, eta), chunk=chunk)
    mask = render.mask.numpy()
    normals = degrade(render.normals.numpy(), mask, config.noise, config.blur_px, config.quantize_8bit,
                      np.random.default_rng(int(seeds[2])))
    return NormalSequence(normals, mask, pixels.numpy().astype(np.float64), tau, theta, eta, config.fps, camera)


def write_sequence(folder: str | Path, sequence: NormalSequence, image_format: str = "png8") -> list[Path]:
    """Write frames (``png8``, ``png16``, ``exr`` images or one ``npy`` stack) and ``truth.csv`` into
    ``folder`` (new, or without such files: ``data.files.fresh_output_folder``)."""
    if image_format not in SEQUENCE_FORMATS:
        raise InputError(f"format={image_format}: expected {', '.join(SEQUENCE_FORMATS)}")
    folder = fresh_output_folder(folder, SEQUENCE_FILES, "out")
    written = []
    if image_format == "npy":
        written.append(folder / "normals.npy")
        save_npy(written[-1], sequence.normals)
    else:
        suffix, bits = {"png8": (".png", 8), "png16": (".png", 16), "exr": (".exr", 8)}[image_format]
        for t, frame in enumerate(sequence.normals):
            written.append(folder / f"frame_{t:05d}{suffix}")
            write_normal_image(written[-1], frame, bits)
    write_tau_track(folder / "truth.csv", TauTrack(sequence.tau, sequence.time, sequence.fps),
                    x_px=sequence.larynx_px[:, 0], y_px=sequence.larynx_px[:, 1],
                    eta=np.full(len(sequence), sequence.eta))
    return written


# --------------------------------------------------------------------------- CLI


def run(cfg) -> NormalSequence:
    """The CLI's work for a composed ``configs/normal_sequences.yaml`` (tests call this in-process)."""
    from models.rig import HeadNeckModel

    config = config_dataclass(SequenceConfig, cfg, "configs/normal_sequences.yaml", other_keys=CLI_KEYS)
    if cfg.format not in SEQUENCE_FORMATS:
        raise InputError(f"format={cfg.format}: expected {', '.join(SEQUENCE_FORMATS)}")
    fresh_output_folder(cfg.out, SEQUENCE_FILES, "out")   # before rendering: fail fast on a used folder
    started = _time.perf_counter()
    sequence = make_sequence(HeadNeckModel.from_config(cfg.rig), config, int(cfg.seed))
    rendered = _time.perf_counter() - started
    write_sequence(cfg.out, sequence, str(cfg.format))
    print(f"rendered {len(sequence)} frames of {config.size}x{config.size} in {rendered:.1f} s "
          f"({len(sequence) / rendered:.0f} frames/s); wrote {cfg.format} frames and truth.csv to {cfg.out}")
    return sequence


if __name__ == "__main__":
    run_cli("normal_sequences", run)
