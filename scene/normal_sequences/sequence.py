"""A synthetic normal-map sequence of the neck: made from the rig with random head motion, expressions and
tau, degraded like a capture, and written as frames plus ``truth.csv``.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from base.errors import InputError
from base.files import fresh_output_folder, save_npy
from data.expressions import EXPRESSION_NAMES, read_expressions
from data.normals import decode_normals, encode_normals, write_normal_image
from data.synthetic_tau import random_tau_trajectory
from data.tau_track import TauTrack, write_tau_track
from models.rig import HeadNeckModel
from scene.render import DEFAULT_CM_PER_PX, DEFAULT_DISTANCE, DEFAULT_SIZE, Camera, NeckRenderer, neck_camera

SEQUENCE_FORMATS = ("png8", "png16", "exr", "npy")
SEQUENCE_FILES = ("frame_*", "normals.npy", "truth.csv")     # what write_sequence writes into its folder


@dataclass
class SequenceConfig:
    """Generator settings; angles in degrees, tau in UV units, lengths in pixels unless named otherwise."""

    frames: int = 300
    fps: float = 30.0
    size: int = DEFAULT_SIZE              # square frames, pixels
    cm_per_px: float = DEFAULT_CM_PER_PX  # at the depth of the rest larynx point
    perspective: bool = False
    distance: float = DEFAULT_DISTANCE    # cm from the eye to the rest larynx point
    swallows_per_minute: float = 6.0
    speech: float = 0.008                 # std of the speech-like motion, tau units
    drift: float = 0.002                  # slow posture drift amplitude, tau units
    head_motion_deg: float = 3.0          # largest head excursion per axis
    head_motion_hz: float = 0.3           # highest frequency of the head motion
    expressions: str | None = None        # a recording the face replays (read_expressions); None: a still face
    expressions_fps: float | None = None  # its rate, for files without time stamps (.npy, header-less CSV)
    expression_start: float | None = None  # seconds into the recording; None: drawn from the seed
    eta_min: float = 0.8
    eta_max: float = 1.2
    noise: float = 0.05                   # std per normal component, before renormalising
    blur_px: float = 0.0                  # Gaussian blur sigma in pixels (0 = none)
    quantize_8bit: bool = False

    def __post_init__(self) -> None:
        if self.frames < 1 or not self.fps > 0 or self.size < 8 or not self.cm_per_px > 0:
            raise ValueError(f"frames={self.frames}, fps={self.fps}, size={self.size}, cm_per_px={self.cm_per_px}: "
                             f"expected at least 1 frame, a positive fps, at least 8 px and a positive scale")
        if not 0 <= self.eta_min <= self.eta_max:
            raise ValueError(f"eta_min={self.eta_min}, eta_max={self.eta_max}: expected 0 <= eta_min <= eta_max")
        if min(self.noise, self.blur_px, self.head_motion_deg) < 0:
            raise ValueError("noise, blur_px and head_motion_deg must not be negative")


@dataclass
class NormalSequence:
    """A rendered sequence and its truth.

    normals [T,H,W,3] float32 camera-space normals (0 on the background); mask [T,H,W] bool;
    larynx_px [T,2] (col, row) ground-truth larynx point; slide_px [T,2] the same with the head still;
    tau [T] UV units; theta [T,8,3] radians, axis-angle per joint in the ANATOMICAL joint frames (x flexion,
    y axial rotation, z lateral bending; the rig's bone-frame input is ``rig.from_anatomical(theta)``);
    psi [T,E] the expression weights (zeros without a recording); eta larynx size; fps; camera the view.
    """

    normals: np.ndarray
    mask: np.ndarray
    larynx_px: np.ndarray
    slide_px: np.ndarray
    tau: np.ndarray
    theta: np.ndarray
    psi: np.ndarray
    eta: float
    fps: float
    camera: Camera

    @property
    def time(self) -> np.ndarray:
        return np.arange(len(self.tau)) / self.fps

    def __len__(self) -> int:
        return len(self.tau)

    def ceiling_r2(self) -> float:
        """:func:`tau_r2` of the true image position of the larynx (its rise ``-larynx_px[:, 1]``): what
        tracking the image position perfectly gives; above it only with the head's motion compensated."""
        return tau_r2(self.tau, -self.larynx_px[:, 1])


def tau_r2(tau: np.ndarray, rise: np.ndarray) -> float:
    """R^2 of tau [T] fitted by least squares as ``a + b * rise`` from a rise in pixels [T] (e.g. a
    tracker's ``tau_px``): the squared correlation of the two; NaN rows are left out; 0 for a constant."""
    tau, rise = np.asarray(tau, np.float64), np.asarray(rise, np.float64)
    keep = np.isfinite(tau) & np.isfinite(rise)
    tau, rise = tau[keep] - tau[keep].mean(), rise[keep] - rise[keep].mean()
    den = float((tau * tau).sum() * (rise * rise).sum())
    return float((tau * rise).sum() ** 2 / den) if den > 0 else 0.0


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


def expression_window(path: str | Path, names: list[str], num_frames: int, fps: float, seed: int,
                      start: float | None = None, recording_fps: float | None = None) -> np.ndarray:
    """Expression weights psi [T,E] (columns in the rig's ``names`` order) replaying a recording.

    The recording (``data.expressions.read_expressions``; ``recording_fps`` for files without time stamps)
    is resampled to ``fps`` and read from ``start`` seconds (None: a start drawn from ``seed`` such that the
    window fits when it can), looping over its end when the window is longer.
    """
    track = read_expressions(path, fps=recording_fps, fps_key="expressions_fps").resampled(fps)
    hack = {name: k for k, name in enumerate(EXPRESSION_NAMES)}       # the reader's column order
    missing = [n for n in names if n not in hack]
    if missing:
        raise InputError(f"{path}: the rig's expressions {missing[:3]} have no column in the recording")
    length = len(track)
    if start is None:
        first = int(np.random.default_rng(seed).integers(0, max(1, length - num_frames + 1)))
    else:
        if not 0 <= start <= track.time[-1]:
            raise InputError(f"expression_start={start:g}: outside the recording {path} (0..{track.time[-1]:.2f} s)")
        first = int(round(start * fps))
    rows = (first + np.arange(num_frames)) % length
    return track.psi[rows][:, [hack[n] for n in names]].astype(np.float32)


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


def make_sequence(rig: HeadNeckModel, config: SequenceConfig, seed: int, chunk: int = 8) -> NormalSequence:
    """Render a synthetic sequence of ``config.frames`` frames (deterministic from ``seed``).

    rig: a ``models.rig.HeadNeckModel``.  Returns the frames and their truth (:class:`NormalSequence`).
    """
    rng = np.random.default_rng(seed)
    seeds = rng.integers(2**31, size=4)
    tau, _ = random_tau_trajectory(config.frames, config.fps, int(seeds[0]), config.swallows_per_minute,
                                   config.speech, config.drift)
    theta = head_motion(config.frames, config.fps, int(seeds[1]), config.head_motion_deg, config.head_motion_hz,
                        rig.num_joints)
    eta = float(rng.uniform(config.eta_min, config.eta_max))
    if config.expressions:
        psi = expression_window(config.expressions, list(rig.expression_names), config.frames, config.fps,
                                int(seeds[3]), config.expression_start, config.expressions_fps)
    else:
        psi = np.zeros((config.frames, rig.num_expressions), np.float32)
    camera = neck_camera(rig, config.size, config.cm_per_px, config.perspective, config.distance)
    renderer = NeckRenderer(rig, camera)
    theta_t = rig.from_anatomical(torch.tensor(theta, dtype=torch.float32))       # bone frames: the rig's input
    tau_t = torch.tensor(tau, dtype=torch.float32)
    eta_t = torch.full_like(tau_t, eta)
    psi_t = torch.as_tensor(psi)
    render, pixels = renderer.render_with_truth(theta_t, psi_t, tau_t, eta_t, chunk=chunk)
    _, still = renderer.pose(torch.zeros_like(theta_t), psi_t, tau_t, eta_t)
    mask = render.mask.numpy()
    normals = degrade(render.normals.numpy(), mask, config.noise, config.blur_px, config.quantize_8bit,
                      np.random.default_rng(int(seeds[2])))
    return NormalSequence(normals, mask, pixels.numpy().astype(np.float64), still.numpy().astype(np.float64), tau,
                          theta, psi, eta, config.fps, camera)


def write_sequence(folder: str | Path, sequence: NormalSequence, image_format: str = "png8") -> list[Path]:
    """Write frames (``png8``, ``png16``, ``exr`` images or one ``npy`` stack) and ``truth.csv`` into
    ``folder`` (new, or without such files: ``base.files.fresh_output_folder``); returns the frame files."""
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
                    slide_x_px=sequence.slide_px[:, 0], slide_y_px=sequence.slide_px[:, 1],
                    eta=np.full(len(sequence), sequence.eta))
    return written
