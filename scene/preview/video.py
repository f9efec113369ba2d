"""Preview panels (one character's renders and strip) put side by side per output frame and written as an
mp4 (OpenCV, mp4v, through a temporary file renamed when complete).
"""
from __future__ import annotations

import os
import time as timer
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from base.errors import InputError
from base.files import atomic_path
from data.params import AnimationParams
from models.rig import HeadNeckModel
from scene.characters import person_rig
from scene.preview.strip import Strip, make_strip
from scene.preview.view import SHADINGS, framing_camera, posed_vertices, shade
from scene.render import Camera, outward_faces, render_normals

STRIP_FRACTION = 0.34          # strip height relative to the render's width


@dataclass
class Panel:
    """One character's column of the video: its rig, clip, camera, triangles and strip."""

    rig: HeadNeckModel
    params: AnimationParams
    camera: Camera
    faces: torch.Tensor
    strip: Strip | None
    shading: str

    @classmethod
    def create(cls, rig: HeadNeckModel, params: AnimationParams, size: int = 256, view: str = "front",
               shading: str = "shaded", strip: bool = True) -> Panel:
        if shading not in SHADINGS:
            raise InputError(f"shading={shading}: expected one of {', '.join(SHADINGS)}")
        if size < 32 or size % 2:
            raise InputError(f"size={size}: expected an even number of pixels >= 32")
        strip_height = 2 * int(round(size * STRIP_FRACTION / 2))
        rig = person_rig(rig, params, str(params.producers.get("source", "params")))  # a fitted person's shape
        return cls(rig, params, framing_camera(rig, params, view, size),
                   outward_faces(rig.template, rig.faces.numpy()),
                   make_strip(rig, params, size, strip_height) if strip else None, shading)

    def frames(self, frames: np.ndarray) -> np.ndarray:
        """BGR images [B,H,W,3] uint8 of ``frames`` of the clip (render over strip)."""
        rendered = render_normals(posed_vertices(self.rig, self.params, frames), self.faces, self.camera)
        images = shade(rendered.normals.numpy(), rendered.mask.numpy(), self.shading)
        if self.strip is None:
            return images
        strips = np.stack([self.strip.draw(int(i)) for i in frames])
        return np.concatenate([images, strips], axis=1)


def output_frames(params: AnimationParams, fps: float | None) -> tuple[np.ndarray, float]:
    """(clip frame shown at each video frame [T'], video fps): every frame at the clip's rate, or the
    clip frame nearest each tick of ``fps``."""
    if fps is None:
        return np.arange(len(params)), float(params.fps)
    if not fps > 0:
        raise InputError(f"fps={fps}: expected a positive frame rate")
    ticks = params.time[0] + np.arange(int(np.floor((params.time[-1] - params.time[0]) * fps + 1e-9)) + 1) / fps
    right = np.clip(np.searchsorted(params.time, ticks), 1, max(len(params) - 1, 1))
    left = right - 1
    nearest = np.where(np.abs(params.time[np.minimum(right, len(params) - 1)] - ticks)
                       < np.abs(params.time[left] - ticks), right, left)
    return np.minimum(nearest, len(params) - 1), float(fps)


@dataclass
class PreviewReport:
    """path, frames written, video fps, size (width, height), seconds spent, frames rendered per second."""

    path: Path
    frames: int
    fps: float
    size: tuple[int, int]
    seconds: float

    @property
    def frames_per_second(self) -> float:
        return self.frames / max(self.seconds, 1e-9)

    def summary(self) -> str:
        speed = self.frames_per_second
        return (f"wrote {self.path}: {self.frames} frames {self.size[0]}x{self.size[1]} at {self.fps:g} fps, "
                f"rendered at {speed:.1f} frames/s ({speed / self.fps:.2f}x real time)")


def write_preview(path: str | os.PathLike, panels: list[Panel], fps: float | None = None,
                  chunk: int = 16) -> PreviewReport:
    """Render ``panels`` side by side (their clips' frames matched by index; the first sets the timing)
    into an mp4 at ``path``, atomically.

    Args:
        path: the ``.mp4`` to write.
        panels: one or more :class:`Panel` (``Panel.create(rig, params, size, view, shading)``).
        fps: the video's rate (None: the first clip's; else the clip frame nearest each tick).
        chunk: frames posed and rendered together.
    Returns:
        PreviewReport.
    """
    started = timer.perf_counter()
    path = Path(path)
    if path.suffix.lower() != ".mp4":
        raise InputError(f"out={path}: expected an .mp4 file")
    if not panels:
        raise ValueError("write_preview needs at least one panel")
    frames, rate = output_frames(panels[0].params, fps)
    lengths = [len(p.params) for p in panels]
    if len(set(lengths)) > 1:
        raise InputError(f"the clips side by side have different lengths ({lengths} frames); retarget the same clip")
    height = panels[0].camera.height + (panels[0].strip.base.shape[0] if panels[0].strip is not None else 0)
    width = sum(p.camera.width for p in panels)
    with atomic_path(path) as tmp:
        writer = cv2.VideoWriter(str(tmp), cv2.VideoWriter_fourcc(*"mp4v"), rate, (width, height))
        if not writer.isOpened():
            raise OSError(f"{path}: OpenCV cannot write mp4 video here")
        try:
            for start in range(0, len(frames), chunk):
                batch = frames[start:start + chunk]
                images = np.concatenate([p.frames(batch) for p in panels], axis=2)
                for image in images:
                    writer.write(np.ascontiguousarray(image))
        finally:
            writer.release()
    return PreviewReport(path, len(frames), rate, (width, height), timer.perf_counter() - started)


def preview_image(panels: list[Panel], frame: int) -> np.ndarray:
    """One frame of the preview [H,W,3] BGR uint8 (for a still, e.g. the README's)."""
    return np.concatenate([p.frames(np.array([frame])) for p in panels], axis=2)[0]
