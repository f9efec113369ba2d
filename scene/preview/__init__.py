"""Preview video of a clip: the posed mesh rendered per frame, with tau and the joint angles as a strip.

    python -m scene.preview source=params.npz out=preview.mp4 [size=256] [view=front|side|three_quarter]
        [shading=shaded|normals] [fps=30] [second=giraffe_params.npz]

Each frame is the rig posed by the clip (``rig(theta, psi, tau, eta)``), rendered orthographically with the
project's rasteriser (``scene.render.render_normals``) from a view turned about the vertical axis
(front: from +z; side: from the subject's left, +x; three_quarter: half way), framed on the clip's
posed meshes, and shown shaded (Lambert, a light over the camera's shoulder) or as the normal map.  Under
it a strip plots the clip's tau and the cervical angles summed over the joints (flexion, axial rotation,
lateral bend in the anatomical frames, degrees) with a cursor at the frame, and bars of the 8 joints'
angles at the frame.  ``second=`` adds a second character beside it (e.g. the giraffe retargeted from
the same clip), each with its own strip.  The video is written with OpenCV (mp4v) through a temporary
file renamed when complete.
"""
from __future__ import annotations

import os
import time as timer
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch
from omegaconf import MISSING

from base.cli import register_config, to_dataclass
from base.errors import InputError
from base.files import atomic_path
from base.rotations import axis_angle_to_euler
from data.normals import encode_normals
from data.params import AnimationParams, load_params
from models.rig import HeadNeckModel
from scene.gltf import resolve_rig
from scene.render import Camera, outward_faces, render_normals

# Camera azimuth about the world's y axis, degrees; the camera moves from the front (+z) towards the
# subject's left (+x).
VIEWS = {"front": 0.0, "three_quarter": 45.0, "side": 90.0}
SHADINGS = ("shaded", "normals")
MARGIN = 1.08                  # frame the posed meshes with 8 % to spare
LIGHT = np.array([-0.35, 0.45, 0.82])   # camera space: from the upper left, in front
AMBIENT = 0.22
ALBEDO_BGR = np.array([0.52, 0.62, 0.80])  # the GLB's skin colour (scene.gltf.SKIN_COLOUR), BGR
BACKGROUND_BGR = (38, 34, 30)
STRIP_FRACTION = 0.34          # strip height relative to the render's width
ANGLE_COLOURS_BGR = ((80, 80, 240), (90, 200, 90), (240, 150, 60))   # flexion, rotation, bend
TAU_COLOUR_BGR = (60, 220, 240)
BAR_RANGE_DEG = 10.0           # a joint bar at full height
STRIP_TOP, STRIP_BOTTOM = 13, 28   # pixels above and below the strip's plots (labels, two text lines)


def view_rotation(view: str) -> np.ndarray:
    """World -> camera rotation [3,3] (rows: camera x right, y up, z towards the camera) of a named view."""
    if view not in VIEWS:
        raise InputError(f"view={view}: expected one of {', '.join(VIEWS)}")
    a = np.radians(VIEWS[view])
    towards_camera = np.array([np.sin(a), 0.0, np.cos(a)])
    up = np.array([0.0, 1.0, 0.0])
    return np.stack([np.cross(up, towards_camera), up, towards_camera])


@torch.no_grad()
def posed_vertices(rig: HeadNeckModel, params: AnimationParams, frames: np.ndarray) -> torch.Tensor:
    """``rig(theta, psi, tau, eta)`` at ``frames`` of the clip [B,N,3] cm."""
    return rig(torch.as_tensor(params.theta[frames]), torch.as_tensor(params.psi[frames]),
               torch.as_tensor(params.tau[frames]), torch.as_tensor(params.eta[frames]))


def framing_camera(rig: HeadNeckModel, params: AnimationParams, view: str = "front", size: int = 256,
                   samples: int = 24) -> Camera:
    """An orthographic camera of the named view holding the clip's posed meshes (``samples`` frames spread
    over the clip) in a ``size`` x ``size`` image with a margin."""
    rotation = view_rotation(view)
    frames = np.unique(np.linspace(0, len(params) - 1, min(samples, len(params))).round().astype(int))
    points = posed_vertices(rig, params, frames).double().numpy().reshape(-1, 3) @ rotation.T   # camera axes
    low, high = points.min(0), points.max(0)
    centre_camera = (low + high) / 2
    extent = float(max(high[0] - low[0], high[1] - low[1])) * MARGIN
    centre = rotation.T @ centre_camera
    depth = float(high[2] - low[2])
    return Camera(centre=tuple(float(c) for c in centre), width=int(size), height=int(size),
                  cm_per_px=extent / size, rotation=tuple(tuple(float(v) for v in row) for row in rotation),
                  distance=depth + 50.0, perspective=False)


def shade(normals: np.ndarray, mask: np.ndarray, shading: str = "shaded") -> np.ndarray:
    """Camera-space normals [B,H,W,3] and mask [B,H,W] -> BGR images [B,H,W,3] uint8.

    shaded: albedo * (ambient + (1 - ambient) * max(n . light, 0)); normals: the RGB encoding (n + 1) / 2.
    """
    if shading not in SHADINGS:
        raise InputError(f"shading={shading}: expected one of {', '.join(SHADINGS)}")
    normals = np.asarray(normals, np.float32)
    if shading == "normals":
        image = encode_normals(normals)[..., ::-1] * np.float32(255.0)
    else:
        light = (LIGHT / np.linalg.norm(LIGHT)).astype(np.float32)
        lambert = np.maximum(normals @ light, np.float32(0.0))
        image = ALBEDO_BGR.astype(np.float32) * (np.float32(AMBIENT) + np.float32(1.0 - AMBIENT) * lambert)[..., None]
        image *= np.float32(255.0)
    image = np.where(mask[..., None], image + np.float32(0.5), np.array(BACKGROUND_BGR, np.float32))
    return image.astype(np.uint8)


# ----------------------------------------------------------------------------- strip


def anatomical_degrees(rig: HeadNeckModel, theta: np.ndarray) -> np.ndarray:
    """Per-joint (flexion, axial rotation, lateral bend) [T,J,3] degrees in the anatomical frames."""
    with torch.no_grad():
        euler = axis_angle_to_euler(rig.to_anatomical(torch.as_tensor(theta, dtype=torch.float64)))
    return np.degrees(euler.numpy())


@dataclass
class Strip:
    """The strip under a render: ``base`` [h,w,3] BGR with the whole clip's curves, drawn once; ``draw(i)``
    adds the cursor, the frame's values and the joint bars."""

    base: np.ndarray
    time: np.ndarray
    tau: np.ndarray
    angles: np.ndarray          # [T,J,3] degrees
    plot_width: int
    joint_names: list

    def column(self, frame: int) -> int:
        span = max(float(self.time[-1] - self.time[0]), 1e-9)
        return int(round((self.time[frame] - self.time[0]) / span * (self.plot_width - 1)))

    def draw(self, frame: int) -> np.ndarray:
        image = self.base.copy()
        height, width = image.shape[:2]
        x = self.column(frame)
        cv2.line(image, (x, 0), (x, height - 1), (255, 255, 255), 1)
        scale = height / 90.0
        total = self.angles[frame].sum(0)
        font = cv2.FONT_HERSHEY_SIMPLEX
        cv2.putText(image, f"t {self.time[frame]:.2f} s", (3, height - 16), font, 0.32 * scale, (235, 235, 235), 1,
                    cv2.LINE_AA)
        cv2.putText(image, f"tau {self.tau[frame]:+.4f}", (int(width * 0.33), height - 16), font, 0.32 * scale,
                    TAU_COLOUR_BGR, 1, cv2.LINE_AA)
        for k, (name, value) in enumerate(zip(("flex", "rot", "bend"), total)):
            cv2.putText(image, f"{name} {value:+.1f}", (3 + int(width * 0.27 * k), height - 4), font, 0.32 * scale,
                        ANGLE_COLOURS_BGR[k], 1, cv2.LINE_AA)
        cv2.putText(image, "deg", (3 + int(width * 0.81), height - 4), font, 0.32 * scale, (235, 235, 235), 1,
                    cv2.LINE_AA)
        # Joint bars: per joint three bars (flexion, rotation, bend) about a zero line, +-BAR_RANGE_DEG.
        left = self.plot_width + 4
        slot = max((width - left - 2) // len(self.joint_names), 3)
        zero = (STRIP_TOP + height - STRIP_BOTTOM) // 2
        half = (height - STRIP_BOTTOM - STRIP_TOP) // 2
        cv2.line(image, (left, zero), (width - 2, zero), (110, 110, 110), 1)
        bar = max(slot // 4, 1)
        for j in range(len(self.joint_names)):
            for k in range(3):
                value = float(np.clip(self.angles[frame, j, k] / BAR_RANGE_DEG, -1.0, 1.0))
                x0 = left + j * slot + k * bar
                y1 = int(round(zero - value * half))
                cv2.rectangle(image, (x0, min(zero, y1)), (x0 + bar - 1, max(zero, y1)), ANGLE_COLOURS_BGR[k], -1)
        return image


def make_strip(rig: HeadNeckModel, params: AnimationParams, width: int, height: int) -> Strip:
    """The strip of a clip ``width`` x ``height`` pixels: 70 % curves over the whole clip (tau scaled to
    its range, the summed angles to +-their largest magnitude), 30 % joint bars."""
    angles = anatomical_degrees(rig, params.theta)
    tau = np.asarray(params.tau, np.float64)
    base = np.full((height, width, 3), 18, np.uint8)
    plot_width = int(width * 0.7)
    top, bottom = STRIP_TOP, height - STRIP_BOTTOM
    columns = np.linspace(0, plot_width - 1, len(params)) if len(params) > 1 else np.zeros(1)
    if len(params) > 1:
        span = max(float(params.time[-1] - params.time[0]), 1e-9)
        columns = (params.time - params.time[0]) / span * (plot_width - 1)

    def curve(values: np.ndarray, limit: float, colour) -> None:
        mid = (top + bottom) / 2
        rows = mid - np.clip(values / max(limit, 1e-12), -1, 1) * (bottom - top) / 2
        points = np.stack([columns, rows], 1).round().astype(np.int32)
        cv2.polylines(base, [points], False, colour, 1, cv2.LINE_AA)

    cv2.line(base, (0, (top + bottom) // 2), (plot_width - 1, (top + bottom) // 2), (70, 70, 70), 1)
    totals = angles.sum(1)
    limit = float(np.abs(totals).max())
    for k in range(3):
        curve(totals[:, k], limit, ANGLE_COLOURS_BGR[k])
    centre = (tau.max() + tau.min()) / 2
    curve(tau - centre, float(np.abs(tau - centre).max()), TAU_COLOUR_BGR)
    scale = height / 90.0
    cv2.putText(base, f"tau {tau.min():+.3f}..{tau.max():+.3f}", (3, 10), cv2.FONT_HERSHEY_SIMPLEX,
                0.3 * scale, TAU_COLOUR_BGR, 1, cv2.LINE_AA)
    cv2.putText(base, f"angles +-{limit:.0f} deg", (int(plot_width * 0.55), 10), cv2.FONT_HERSHEY_SIMPLEX,
                0.3 * scale, (200, 200, 200), 1, cv2.LINE_AA)
    return Strip(base, np.asarray(params.time), tau, angles, plot_width, list(params.joint_names))


# ----------------------------------------------------------------------------- frames and video


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


# ----------------------------------------------------------------------------- command line


@dataclass
class PreviewConfig:
    """``python -m scene.preview`` settings (``configs/preview.yaml``).

    source: params.npz; out: the .mp4; rig: a rig file overriding the one recorded in source; size:
    pixels of each render (square, even); view: front | side | three_quarter; shading: shaded | normals;
    fps: video rate (None: the clip's); strip: draw the tau/angle strip; second: a second params.npz shown
    beside the first (e.g. the giraffe retargeted from it), second_rig: its rig override; still: also
    write this PNG of frame ``still_frame``.
    """

    source: str = MISSING
    out: str = MISSING
    rig: str | None = None
    size: int = 256
    view: str = "front"
    shading: str = "shaded"
    fps: float | None = None
    strip: bool = True
    second: str | None = None
    second_rig: str | None = None
    still: str | None = None
    still_frame: int = 0
    threads: int = 1

    def __post_init__(self) -> None:
        if self.view not in VIEWS:
            raise ValueError(f"view={self.view}: expected one of {', '.join(VIEWS)}")
        if self.shading not in SHADINGS:
            raise ValueError(f"shading={self.shading}: expected one of {', '.join(SHADINGS)}")
        if self.size < 32 or self.size % 2:
            raise ValueError(f"size={self.size}: expected an even number of pixels >= 32")
        if self.fps is not None and not self.fps > 0:
            raise ValueError(f"fps={self.fps}: expected a positive frame rate")


register_config("preview_schema", PreviewConfig)


def run(cfg) -> PreviewReport:
    """``python -m scene.preview``: render the clip(s) and print the report."""
    settings = to_dataclass(cfg, PreviewConfig, where="scene.preview")
    clips = [(settings.source, settings.rig)] + ([(settings.second, settings.second_rig)] if settings.second else [])
    panels = []
    for source, rig_override in clips:
        params = load_params(source)
        rig = resolve_rig(params, source, rig_override)
        panels.append(Panel.create(rig, params, settings.size, settings.view, settings.shading, settings.strip))
    if settings.still and not 0 <= settings.still_frame < len(panels[0].params):
        raise InputError(f"still_frame={settings.still_frame}: {settings.source} has frames "
                         f"0..{len(panels[0].params) - 1}")
    report = write_preview(settings.out, panels, settings.fps)
    print(report.summary())
    if settings.still:
        with atomic_path(settings.still) as tmp:
            if not cv2.imwrite(str(tmp), preview_image(panels, settings.still_frame)):
                raise OSError(f"{settings.still}: OpenCV could not write the image")
        print(f"wrote {settings.still}")
    return report
