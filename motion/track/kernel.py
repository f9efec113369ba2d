"""The larynx kernel and the filter it is matched through.

A kernel ``k`` holds the generic larynx shape as camera-space normals (70x70x3 by default, the paper's
size), its centre the larynx point (``scene.render.larynx_point``) in kernel pixels.  What is matched
(:meth:`LarynxKernel.template`) is the kernel after the band-pass (:func:`bandpass`); for the rig's
kernel (:func:`rig_kernel`) it is the larynx's own normal perturbation, the band-passed rest view minus
the same view without the larynx (eta 0), so the neck around the larynx, which stays put while the
larynx slides, is not part of it.  Each kernel pixel is weighted by a Gaussian window
(:func:`match_window`) whose vertical offset and height the rig can calibrate
(``motion.track.calibration.calibrate_window``).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from base.errors import InputError
from base.files import load_npy
from data.normals import read_normal_image, stored_to_unit
from motion.track.config import UNCALIBRATED_SIGMA_Y_PX, BandpassConfig, WindowConfig
from motion.track.sources import MIN_NORM, check_normal_map, decode_frame, float_is_raw
from scene.render import DEFAULT_CM_PER_PX, NeckRenderer, neck_camera

KERNEL_SIZE = 70                 # the paper's 70x70x3 kernel, pixels at 0.08 cm/px (5.6 cm)
# A neck filling the frame (6.4 cm on 256 px at 40 px/cm, real and built-in rig, the larynx rising to the
# frame's top edge): R^2 0.873 / 0.954 with the 5.6 cm kernel, 0.871 / 0.952 with 4.0 cm (5/8 of the frame),
# 0.865 / 0.944 with 3.2 cm, 0.510 / 0.952 with 2.4 cm (benchmarks/README.md); 5/8 costs a third less to set up.
KERNEL_FRAME_SHARE = 0.625
CONTEXT_MARGIN = 96              # px of rendered view around the rig's kernel (band-pass context)


def kernel_size_at(cm_per_px: float, frame: tuple[int, ...] | None = None) -> int:
    """The kernel's side in pixels at ``cm_per_px``: ``KERNEL_SIZE`` at 0.08 cm/px, the same 5.6 cm at others,
    and at most ``KERNEL_FRAME_SHARE`` of the short side of frames of shape ``frame`` (h, w, ...) when given."""
    size = int(round(KERNEL_SIZE * DEFAULT_CM_PER_PX / float(cm_per_px)))
    if frame is not None:
        size = min(size, int(KERNEL_FRAME_SHARE * min(frame[:2])))
    return max(5, size)


def bandpass(normals: np.ndarray, config: BandpassConfig) -> np.ndarray:
    """Normals [H,W,3] -> the band the larynx lives in (float32 [H,W,3]): a Gaussian low-pass of sigma
    ``lowpass_sigma_px``, minus its running mean along each row over ``row_highpass_px``, minus the
    result's running mean along each column over ``column_highpass_px`` (borders reflected; a zero
    setting skips its step).  The high-passes remove the neck's own relief (jaw line and shading along
    rows, the neck's sides and muscles along columns), the low-pass pixel noise and mesh facets."""
    out = np.asarray(normals, dtype=np.float32)
    if config.lowpass_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), config.lowpass_sigma_px, borderType=cv2.BORDER_REFLECT)
    if config.row_highpass_px > 1:
        out = out - cv2.blur(out, (int(config.row_highpass_px), 1), borderType=cv2.BORDER_REFLECT)
    if config.column_highpass_px > 1:
        out = out - cv2.blur(out, (1, int(config.column_highpass_px)), borderType=cv2.BORDER_REFLECT)
    return out


def bandpass_margins(config: BandpassConfig) -> tuple[int, int]:
    """(rows, cols) of context the band-pass needs around a region for its values there to be those of
    the whole image (OpenCV's Gaussian reaches 4 sigma)."""
    blur = int(math.ceil(4 * config.lowpass_sigma_px)) + 1 if config.lowpass_sigma_px > 0 else 0
    return blur + int(config.column_highpass_px) // 2, blur + int(config.row_highpass_px) // 2


@dataclass
class LarynxKernel:
    """A larynx kernel.

    normals [h,w,3] float32 camera-space normals of the larynx and its surroundings (what the raw
    correlation baseline matches); centre (x, y) the kernel-pixel coordinates of the larynx point;
    cm_per_px its scale if known; source a description.

    context [H',W',3] (optional): the image the kernel was cut from, the kernel's top-left pixel at
    ``offset`` (col, row); the band-pass then sees the same neighbourhood as in the frames (without it
    the kernel's borders are reflected).  background [H',W',3] (optional, with a context): the same view
    without the larynx (the rig rendered with eta = 0); the matched template is then the larynx's own
    normal perturbation, bandpass(context) - bandpass(background), cut at the kernel.
    window (optional): the calibrated (offset_y, sigma_y) of the match window in pixels
    (``calibrate_window``); used where the tracker's window settings are None.
    """

    normals: np.ndarray
    centre: tuple[float, float]
    cm_per_px: float | None = None
    source: str = ""
    context: np.ndarray | None = None
    offset: tuple[int, int] = (0, 0)
    background: np.ndarray | None = None
    window: tuple[float, float] | None = None

    def __post_init__(self) -> None:
        self.normals = np.ascontiguousarray(self.normals, dtype=np.float32)
        self.centre = (float(self.centre[0]), float(self.centre[1]))
        self.offset = (int(self.offset[0]), int(self.offset[1]))
        for name in ("context", "background"):
            if getattr(self, name) is not None:
                setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float32))
        if self.background is not None and (self.context is None or self.background.shape != self.context.shape):
            raise ValueError("a kernel's background must come with a context of the same shape")

    def template(self, config: BandpassConfig) -> np.ndarray:
        """The kernel as matched [h,w,3]: band-passed over its context, minus its band-passed background."""
        if self.context is None:
            return np.ascontiguousarray(bandpass(self.normals, config))
        (w, h), (x0, y0) = self.size, self.offset
        out = bandpass(self.context, config)[y0:y0 + h, x0:x0 + w]
        if self.background is not None:
            out = out - bandpass(self.background, config)[y0:y0 + h, x0:x0 + w]
        return np.ascontiguousarray(out)

    @property
    def size(self) -> tuple[int, int]:
        """(width, height)."""
        return self.normals.shape[1], self.normals.shape[0]


def match_window(kernel: LarynxKernel, config: WindowConfig) -> np.ndarray | None:
    """The weight [h,w] float32 of each kernel pixel in the match: a Gaussian of sigmas
    (``sigma_x_px``, ``sigma_y``) centred ``offset_y`` rows below the kernel's centre; None (all pixels
    alike) when either sigma is 0.  ``offset_y`` / ``sigma_y``: the config's, or where None the kernel's
    calibrated window (:attr:`LarynxKernel.window`), else 0 / 14 px."""
    offset, sigma_y = window_geometry(kernel, config)
    if config.sigma_x_px <= 0 or sigma_y <= 0:
        return None
    w, h = kernel.size
    rows, cols = np.mgrid[0:h, 0:w]
    dx, dy = (cols - kernel.centre[0]) / config.sigma_x_px, (rows - kernel.centre[1] - offset) / sigma_y
    return np.exp(-0.5 * (dx * dx + dy * dy)).astype(np.float32)


def window_geometry(kernel: LarynxKernel, config: WindowConfig) -> tuple[float, float]:
    """(offset_y, sigma_y) in pixels of the match window (see :func:`match_window`)."""
    calibrated = kernel.window or (0.0, UNCALIBRATED_SIGMA_Y_PX * _scale_factor(kernel))
    offset = config.offset_y_px if config.offset_y_px is not None else calibrated[0]
    sigma_y = config.sigma_y_px if config.sigma_y_px is not None else calibrated[1]
    return float(offset), float(sigma_y)


def _scale_factor(kernel: LarynxKernel) -> float:
    return DEFAULT_CM_PER_PX / kernel.cm_per_px if kernel.cm_per_px else 1.0


def rig_kernel(rig, cm_per_px: float = DEFAULT_CM_PER_PX, size: int = KERNEL_SIZE,
               margin: int = CONTEXT_MARGIN) -> LarynxKernel:
    """The generic larynx kernel of ``rig`` (a ``models.rig.HeadNeckModel``).

    The rig at rest (theta 0, psi 0, tau 0, eta 1) in the default neck view at ``cm_per_px``, ``size`` px
    square, centred on the larynx point (its centre is the middle pixel).  Its context is the view
    ``margin`` px wider on each side (``bandpass_margins``: enough for column high-passes up to 160 px),
    its background the same view without the larynx (eta 0).  The window is uncalibrated
    (``calibrate_window`` calibrates it).
    """
    camera = neck_camera(rig, size + 2 * margin, cm_per_px)
    render = NeckRenderer(rig, camera)(rig.neutral(2), eta=torch.tensor([1.0, 0.0]))
    with_larynx, without_larynx = render.normals.numpy()
    if not bool(render.mask[0, margin:margin + size, margin:margin + size].all()):
        raise InputError(f"the {size}x{size} px kernel at {cm_per_px} cm/px reaches beyond the neck; "
                         f"give a smaller kernel_size or a finer cm_per_px")
    c = (size - 1) / 2.0
    return LarynxKernel(with_larynx[margin:margin + size, margin:margin + size], (c, c), float(cm_per_px),
                        f"rig at {cm_per_px:g} cm/px", with_larynx, (margin, margin), without_larynx)


def kernel_from_file(path: str | Path, cm_per_px: float | None = None, float_encoding: str = "auto") -> LarynxKernel:
    """A kernel image (.npy [h,w,3], .png, .tif, .exr; the frames' encoding), centred on its middle pixel;
    ``cm_per_px`` its own pixel scale if known (``rescale_kernel`` then resamples it to the frames')."""
    path = Path(path)
    if path.suffix.lower() == ".npy":
        values = load_npy(path, 3, "a kernel [h,w,3]")
        if values.shape[2] != 3:
            raise InputError(f"{path}: array of shape {values.shape}, expected a kernel [h,w,3]")
        values, is_float = stored_to_unit(values, str(path))
    else:
        values, is_float = read_normal_image(path)
    normals = decode_frame(values, is_float and float_is_raw(values, float_encoding))
    check_normal_map(normals, str(path))
    h, w = normals.shape[:2]
    return LarynxKernel(normals, ((w - 1) / 2.0, (h - 1) / 2.0), cm_per_px, str(path))


def kernel_from_frame(normals: np.ndarray, x: float, y: float, size: int = KERNEL_SIZE, label: str = "frame 0",
                      cm_per_px: float | None = None) -> LarynxKernel:
    """The ``size`` px square of a frame [H,W,3] around (x, y); its centre is (x, y) in kernel coordinates."""
    h, w = normals.shape[:2]
    if size > min(h, w):
        raise InputError(f"{label}: kernel of {size} px does not fit a {w}x{h} frame")
    if not (0 <= x <= w - 1 and 0 <= y <= h - 1):
        raise InputError(f"{label}: init position ({x:g}, {y:g}) lies outside the {w}x{h} frame")
    x0 = int(np.clip(round(x - (size - 1) / 2.0), 0, w - size))
    y0 = int(np.clip(round(y - (size - 1) / 2.0), 0, h - size))
    return LarynxKernel(normals[y0:y0 + size, x0:x0 + size], (x - x0, y - y0), cm_per_px,
                        f"{label} at ({x:g}, {y:g})", np.array(normals, dtype=np.float32), (x0, y0))


def rescale_kernel(kernel: LarynxKernel, cm_per_px: float) -> LarynxKernel:
    """The kernel resampled to ``cm_per_px`` (a no-op when its own scale is unknown or equal); a calibrated
    window is rescaled with it."""
    if kernel.cm_per_px is None or math.isclose(kernel.cm_per_px, cm_per_px, rel_tol=1e-6):
        return kernel
    factor = kernel.cm_per_px / cm_per_px
    w, h = kernel.size
    size = (max(3, round(w * factor)), max(3, round(h * factor)))
    window = None if kernel.window is None else (kernel.window[0] * factor, kernel.window[1] * factor)

    def resample(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        out = cv2.resize(image, shape, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR)
        norms = np.linalg.norm(out, axis=-1, keepdims=True)
        return np.where(norms > MIN_NORM, out / np.maximum(norms, 1e-6), 0.0).astype(np.float32)

    fx, fy = size[0] / w, size[1] / h  # continuous coordinates: x' = (x + 0.5) * f - 0.5
    source = f"{kernel.source} rescaled to {cm_per_px:g} cm/px"
    if kernel.context is None:
        centre = ((kernel.centre[0] + 0.5) * fx - 0.5, (kernel.centre[1] + 0.5) * fy - 0.5)
        return LarynxKernel(resample(kernel.normals, size), centre, cm_per_px, source, window=window)
    # With a context: resample it (and the background) and cut the kernel from it, so that the kernel,
    # its context and its centre stay on one pixel grid.
    shape = (max(size[0], round(kernel.context.shape[1] * fx)), max(size[1], round(kernel.context.shape[0] * fy)))
    context = resample(kernel.context, shape)
    background = None if kernel.background is None else resample(kernel.background, shape)
    scales = (fx, fy)
    x0, y0 = (int(np.clip(round((o + 0.5) * f - 0.5), 0, n - k))
              for o, f, n, k in zip(kernel.offset, scales, shape, size))
    centre = tuple((o + c + 0.5) * f - 0.5 - o_new
                   for o, c, f, o_new in zip(kernel.offset, kernel.centre, scales, (x0, y0)))
    return LarynxKernel(context[y0:y0 + size[1], x0:x0 + size[0]], centre, cm_per_px, source, context, (x0, y0),
                        background, window)


def with_window(kernel: LarynxKernel, offset_y: float, sigma_y: float) -> LarynxKernel:
    """The kernel with a calibrated match window (offset_y, sigma_y) in its pixels."""
    return replace(kernel, window=(float(offset_y), float(sigma_y)))
