"""Larynx tracking in photometric normal maps (the paper's tau_bar(j) = argmax_x [k * N_j](x) - tau0).

A kernel ``k`` holding the generic larynx shape as normals (70x70x3 by
default) is matched against each normal map ``N_j`` by normalised
correlation; the match's position, minus the rest position, is the larynx
slide in pixels, and with a calibration in tau units.

Input (``open_source``): a folder of images (8/16-bit PNG or TIFF, float
EXR; sorted by name, numbers compared as numbers), a video file (anything
``cv2.VideoCapture`` reads), or a ``.npy`` stack ``[T,H,W,3]``.

Encoding (owned by ``data.render``): RGB = (n_x, n_y, n_z) of the unit
surface normal in CAMERA space, x right, y up, z towards the camera, mapped
from [-1, 1] to [0, 1] as (n + 1) / 2 and scaled to the integer range of
8/16-bit images and videos.  Float data (EXR, float ``.npy``) is read with
``float_encoding``: ``raw`` = the normals themselves in [-1, 1], ``encoded`` =
(n + 1) / 2 in [0, 1], ``auto`` (default) = raw if the first frame has a
negative value, else encoded.  ``.npy`` stacks of uint8 / uint16 are encoded.
Background: pixels whose decoded vector is shorter than 0.5 (e.g. grey) or
longer than 1.5 (black decodes to (-1, -1, -1)); they count as n = 0.
Validation: every frame must have at least 2 % foreground, and at least 80 %
of its foreground (checked on every 4th pixel) must decode to vectors of
norm 1 +- 0.15; otherwise ``InputError`` names the file or frame.

Frame rate: the video's own (``CAP_PROP_FPS``) unless ``fps=`` is given;
``fps=`` (default 30) for image folders and ``.npy`` stacks.

Positions: (x_px, y_px) = (col, row) in the image convention of
``data.render`` (pixel centres at integers, rows go DOWN) of the kernel's
centre point, which for the rig kernel is the rig's larynx point
(``data.render.larynx_point``, also the ground truth of
``data.normal_sequences``).  tau_px = y_rest - y_px (positive = up), the rest
row being the position in frame ``rest_frame`` (default 0);
tau = tau_px / px_per_tau.

Matching (``LarynxTracker``): the kernel's template and each frame's search
window go through the same band-pass (``bandpass``: a Gaussian low-pass of
``lowpass_sigma_px`` = 3 px, minus the running mean along each row over
``row_highpass_px`` = 21 px and along each column over ``column_highpass_px``
= 101 px), which keeps the larynx and drops the neck's own relief and shading,
the jaw line, mesh facets and pixel noise.  The rig kernel's template is the
larynx's normal perturbation: the band-passed rig at rest minus the same view
without the larynx (eta 0), so the neck around the larynx, which stays put
while it slides, is not part of what is matched.  ``cv2.matchTemplate``
TM_CCORR_NORMED (the band-passed values have no mean left to remove) over the
three channels, each kernel pixel weighted by a Gaussian window around the
kernel's centre (``match_window``, sigmas ``window_sigma_x_px`` = 20,
``window_sigma_y_px`` = 14 px: the match follows the larynx's body, whose
centroid is the larynx point), within a search band of +-``band_rows`` rows
and +-``band_cols`` columns around the predicted position (the last accepted
one moved on at constant velocity; the whole frame on the first frame without
``init_x/init_y``, and again after ``reacquire_after`` rejected frames);
sub-pixel peak by a least-squares 2-D quadratic on the 3x3 correlation values
around the maximum.  confidence =
the peak's weighted normalised correlation (clipped to [0, 1]).  A match below
``min_confidence``, further than ``max_jump_px`` (times the frames since the
last accepted one) from the prediction, or lying on the band's border (the
true peak may be beyond it) is rejected: the frame keeps the last accepted
position and gets confidence 0.  Optional smoothing (``smooth_frames`` > 0):
a Gaussian of that sigma in frames, each frame weighted by its confidence
(rejected frames are then filled from their neighbours).  Off by default:
measured in benchmarks/bench_tracker.py.

Accuracy (benchmarks/bench_tracker.py, 0.08 cm/px): on noise-free renders with
tau -0.03..0.06 the tracked rise is 0.95 of the larynx point's on the real
HACK rig (0.2 with the former matching: the rest render as the kernel, an
81 px row high-pass alone, no window) and 1.0 on the built-in rig; on noisy
sequences (noise 0.05, 3 degrees of head motion, swallows) the median / 95th
percentile error is 0.43 / 1.24 px on the real rig (former 1.13 / 13.9) and
0.24 / 0.56 px on the built-in rig (former 0.25 / 0.48).  What remains on the
real rig is its geometry: near tau 0.06 the larynx's cap wraps under the jaw,
where the front view barely sees it (the cap's centroid weighted by its
visible area rises 20 px there against 25.7 px for the centroid itself), and
its coarse mesh (0.5 cm edges) changes the larynx's outline as the map slides
over the vertices (0.7-1.4 px short for tau 0.0075-0.03).

Calibration: ``px_per_tau`` (pixels of upward image motion per tau unit) from
the rig for the default neck view at the capture's ``cm_per_px``
(:func:`rig_px_per_tau`: the larynx point projected at tau = -delta and
+delta), or given by the user; without one the ``tau`` column is NaN.

CLI (hydra, ``configs/track.yaml``)::

    python -m motion.track input=frames/ out=track.csv [init_x=128 init_y=130] [cm_per_px=0.08]
        [kernel=rig|frame|kernel.npy] [rig=hack_rig.npz] [px_per_tau=auto|<number>|null] [fps=30]

writes ``frame,time,x_px,y_px,tau_px,tau,confidence`` and a plot (``plot=``, default beside the CSV).
"""
from __future__ import annotations

import math
import re
import time as _time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterable, Iterator

import cv2
import numpy as np
import torch
from scipy.ndimage import gaussian_filter1d

from data.cli import config_dataclass, run_cli
from data.errors import InputError
from data.files import load_npy, write_csv
from data.plots import figure, save_figure
from data.normals import FLOAT_IMAGE_SUFFIXES, INTEGER_IMAGE_SUFFIXES, decode_normals, read_normal_image, stored_to_unit
from data.render import DEFAULT_CM_PER_PX, NeckRenderer, neck_camera
from motion.signal import parabolic_peak

KERNEL_SIZE = 70                 # the paper's 70x70x3 kernel
DEFAULT_FPS = 30.0               # image folders and .npy stacks carry no frame rate
MIN_NORM = 0.5                   # decoded vectors shorter than this (grey) are background
MAX_NORM = 1.5                   # ... and longer than this (black decodes to (-1,-1,-1), length 1.73)
UNIT_TOLERANCE = 0.15            # | |n| - 1 | allowed for a foreground pixel to count as a normal
MIN_UNIT_FRACTION = 0.8          # share of foreground pixels that must be unit normals
MIN_FOREGROUND = 0.02            # share of the frame that must be foreground


# --------------------------------------------------------------------------- decoding and validation


def float_is_raw(values: np.ndarray, float_encoding: str) -> bool:
    """Whether float data ``values`` holds raw normals in [-1, 1] (else the encoding (n + 1) / 2):
    ``float_encoding`` raw / encoded, or auto = raw if any value is negative (see the module doc)."""
    if float_encoding == "auto":
        return bool(values.min() < 0)
    return float_encoding == "raw"


def decode_frame(rgb: np.ndarray, is_raw: bool) -> np.ndarray:
    """Stored values [H,W,3] -> camera-space normals float32 [H,W,3], background 0 (see the module doc)."""
    rgb = np.asarray(rgb, dtype=np.float32)
    normals = rgb.copy() if is_raw else decode_normals(rgb)
    norm2 = cv2.transform(normals * normals, np.ones((1, 3), np.float32))      # |n|^2 per pixel [H,W]
    normals[(norm2 < MIN_NORM**2) | (norm2 > MAX_NORM**2)] = 0.0
    return normals


def check_normal_map(normals: np.ndarray, label: str) -> None:
    """Raise InputError naming ``label`` unless ``normals`` [H,W,3] (decoded) looks like a normal map."""
    if normals.ndim != 3 or normals.shape[2] != 3:
        raise InputError(f"{label}: array of shape {normals.shape}, expected an RGB normal map [H,W,3]")
    sample = normals[::4, ::4].reshape(-1, 3)
    norms = np.linalg.norm(sample, axis=1)
    foreground = norms > 0
    share = foreground.mean()
    if share < MIN_FOREGROUND:
        raise InputError(f"{label}: only {100 * share:.1f}% of the pixels hold a normal (the rest decodes to "
                         f"vectors shorter than {MIN_NORM} or longer than {MAX_NORM}: background); expected a "
                         f"normal map with RGB = (n + 1) / 2")
    unit = np.abs(norms[foreground] - 1.0) < UNIT_TOLERANCE
    if unit.mean() < MIN_UNIT_FRACTION:
        raise InputError(
            f"{label}: not a normal map: only {100 * unit.mean():.0f}% of the foreground pixels decode to unit "
            f"vectors (median norm {np.median(norms[foreground]):.2f}); expected RGB = (n + 1) / 2 of unit normals "
            f"(x right, y up, z towards the camera), or raw normals in [-1, 1] for float data (float_encoding)")


# --------------------------------------------------------------------------- sources


def _natural_key(path: Path) -> list:
    return [int(part) if part.isdigit() else part.lower() for part in re.split(r"(\d+)", path.name)]


@dataclass
class NormalMapSource:
    """Frames of normal maps from a folder, a video or a .npy stack.

    ``frames()`` yields (index, label, normals float32 [H,W,3]) decoded and validated; ``label`` names the
    file or frame for error messages.  ``count`` is the number of frames (a video's is its header's).
    """

    path: Path
    kind: str
    fps: float
    count: int
    float_encoding: str = "auto"
    files: list[Path] = field(default_factory=list)
    _raw: bool | None = None

    def _is_raw(self, values: np.ndarray, is_float: bool) -> bool:
        if not is_float:
            return False
        if self._raw is None:  # decided on the first float frame, kept for the whole source
            self._raw = float_is_raw(values, self.float_encoding)
        return self._raw

    def _decoded(self, values: np.ndarray, is_float: bool, label: str, shape: list) -> np.ndarray:
        normals = decode_frame(values, self._is_raw(values, is_float))
        if not shape:
            shape.append(normals.shape)
        elif normals.shape != shape[0]:
            raise InputError(f"{label}: frame of size {normals.shape[1]}x{normals.shape[0]}, expected "
                             f"{shape[0][1]}x{shape[0][0]} as the first frame")
        check_normal_map(normals, label)
        return normals

    def frames(self) -> Iterator[tuple[int, str, np.ndarray]]:
        shape: list = []
        if self.kind == "folder":
            for i, file in enumerate(self.files):
                values, is_float = read_normal_image(file)
                yield i, str(file), self._decoded(values, is_float, str(file), shape)
        elif self.kind == "npy":
            stack = np.load(self.path, mmap_mode="r", allow_pickle=False)
            for i in range(len(stack)):
                label = f"{self.path}: frame {i}"
                values, is_float = stored_to_unit(stack[i], label)
                if not np.isfinite(values).all():
                    raise InputError(f"{label}: non-finite values; expected a normal map")
                yield i, label, self._decoded(values, is_float, label, shape)
        else:
            capture = cv2.VideoCapture(str(self.path))
            try:
                i = 0
                while True:
                    ok, image = capture.read()
                    if not ok:
                        break
                    label = f"{self.path}: frame {i}"
                    if image.ndim != 3 or image.shape[2] < 3:
                        raise InputError(f"{label}: {image.shape}, expected 3-channel colour frames")
                    values, is_float = stored_to_unit(image[..., 2::-1], label)
                    yield i, label, self._decoded(values, is_float, label, shape)
                    i += 1
            finally:
                capture.release()
            if i == 0:
                raise InputError(f"{self.path}: the video has no readable frames")


VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")


def open_source(path: str | Path, fps: float | None = None, float_encoding: str = "auto") -> NormalMapSource:
    """A folder of images, a video file or a .npy stack [T,H,W,3] (see the module doc for the encoding)."""
    path = Path(path)
    if float_encoding not in ("auto", "raw", "encoded"):
        raise InputError(f"float_encoding={float_encoding}: expected auto, raw or encoded")
    if fps is not None and not fps > 0:
        raise InputError(f"fps={fps}: expected a positive frame rate")
    if not path.exists():
        raise InputError(f"{path}: not found; expected a folder of normal-map images, a video or a .npy stack")
    if path.is_dir():
        suffixes = INTEGER_IMAGE_SUFFIXES + FLOAT_IMAGE_SUFFIXES
        files = sorted((p for p in path.iterdir() if p.suffix.lower() in suffixes and not p.name.startswith(".")),
                       key=_natural_key)
        if not files:
            raise InputError(f"{path}: no normal-map images ({', '.join(suffixes)}) in the folder")
        return NormalMapSource(path, "folder", float(fps or DEFAULT_FPS), len(files), float_encoding, files)
    if path.suffix.lower() == ".npy":
        header = np.load(path, mmap_mode="r", allow_pickle=False) if path.stat().st_size else None
        if header is None or header.ndim != 4 or header.shape[-1] != 3:
            shape = None if header is None else header.shape
            raise InputError(f"{path}: array of shape {shape}, expected a normal-map stack [T,H,W,3]")
        if not (np.issubdtype(header.dtype, np.floating) or header.dtype in (np.uint8, np.uint16)):
            raise InputError(f"{path}: dtype {header.dtype}, expected float, uint8 or uint16")
        return NormalMapSource(path, "npy", float(fps or DEFAULT_FPS), len(header), float_encoding)
    if path.suffix.lower() in VIDEO_SUFFIXES:
        capture = cv2.VideoCapture(str(path))
        try:
            if not capture.isOpened():
                raise InputError(f"{path}: OpenCV cannot open this video")
            video_fps = capture.get(cv2.CAP_PROP_FPS)
            count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        finally:
            capture.release()
        rate = fps or (video_fps if video_fps and video_fps > 0 else None)
        if rate is None:
            raise InputError(f"{path}: the video reports no frame rate; give fps=...")
        return NormalMapSource(path, "video", float(rate), count, float_encoding)
    raise InputError(f"{path}: unsupported input '{path.suffix}'; expected a folder of images, a video "
                     f"({', '.join(VIDEO_SUFFIXES)}) or a .npy stack")


# --------------------------------------------------------------------------- band-pass and settings


@dataclass
class TrackerConfig:
    """Matching settings (mirrored by ``configs/track.yaml: tracker``); pixels and frames.

    The defaults suit the default neck view (``DEFAULT_CM_PER_PX`` = 0.08 cm/px, a larynx ~55 px wide and
    ~90 px tall); :meth:`at_scale` gives the same physical sizes at another pixel scale (the CLI applies
    it for ``cm_per_px=``).
    """

    band_rows: int = 24             # search +- rows around the last position (a swallow moves < 8 px/frame at 30 fps)
    band_cols: int = 8              # search +- columns
    lowpass_sigma_px: float = 3.0   # Gaussian low-pass sigma (0 = off), frames and kernel alike
    row_highpass_px: int = 21       # width of the running mean removed along each row (0 = off)
    column_highpass_px: int = 101   # height of the running mean removed along each column (0 = off)
    window_sigma_x_px: float = 20.0  # Gaussian weight of the match around the kernel's centre (0 = uniform)
    window_sigma_y_px: float = 14.0
    max_jump_px: float = 10.0       # largest accepted distance from the prediction, per frame since the last match
    min_confidence: float = 0.2     # lowest accepted peak (weighted) NCC; the real HACK larynx under the jaw: 0.33+
    reacquire_after: int = 10       # consecutive rejections before searching the whole frame again
    subpixel: bool = True
    smooth_frames: float = 0.0      # sigma (frames) of the confidence-weighted Gaussian smoothing; 0 = off


    def at_scale(self, cm_per_px: float) -> "TrackerConfig":
        """The same settings in pixels of a capture at ``cm_per_px`` (lengths scale by 0.08 / cm_per_px)."""
        factor = DEFAULT_CM_PER_PX / float(cm_per_px)

        def odd(width: int) -> int:  # running means keep an odd width, so they stay centred
            return 0 if width <= 1 else max(3, int(round(width * factor)) // 2 * 2 + 1)

        return replace(self, band_rows=max(2, round(self.band_rows * factor)),
                       band_cols=max(1, round(self.band_cols * factor)),
                       lowpass_sigma_px=self.lowpass_sigma_px * factor,
                       row_highpass_px=odd(self.row_highpass_px), column_highpass_px=odd(self.column_highpass_px),
                       window_sigma_x_px=self.window_sigma_x_px * factor,
                       window_sigma_y_px=self.window_sigma_y_px * factor, max_jump_px=self.max_jump_px * factor)


def bandpass(normals: np.ndarray, config: TrackerConfig) -> np.ndarray:
    """Normals [H,W,3] -> the band the larynx lives in (float32 [H,W,3]): a Gaussian low-pass of sigma
    ``lowpass_sigma_px``, minus its running mean along each row over ``row_highpass_px``, minus the
    result's running mean along each column over ``column_highpass_px`` (borders reflected; a zero
    setting skips its step).

    Measured with the other settings at their defaults (``benchmarks/bench_tracker.py``; rise = the
    tracked rise over the larynx point's on noise-free renders, tau -0.03..0.06 at 0.08 cm/px; errors
    on noisy sequences, noise 0.05 and 3 degrees of head motion):

    - The high-passes remove the neck's own relief, which stays put while the larynx slides and holds
      back any kernel cut around it: the jaw line and the neck's shading run along rows, the neck's
      sides and muscles along columns.  On the real HACK rig (its larynx sits 2 cm below the jaw line)
      the rise is 0.2 with the former 81 px row high-pass of the rest render, 0.92 with the 21 px row
      high-pass and 0.95 with the column high-pass added (noisy median 0.57 -> 0.43 px).  On the
      built-in rig's smooth neck the column high-pass changes little (median 0.21 px without, 0.24).
    - The low-pass removes the pixel noise and the faceting of a coarse mesh (HACK's neck has 0.5 cm =
      6 px edges; interpolated vertex normals crease along them, and the creases stay put as the larynx
      slides).  Without it the noisy median error is 1.6 px instead of 0.24 (built-in) and 1.0 px
      instead of 0.43 (real rig).
    """
    out = np.asarray(normals, dtype=np.float32)
    if config.lowpass_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), config.lowpass_sigma_px, borderType=cv2.BORDER_REFLECT)
    if config.row_highpass_px > 1:
        out = out - cv2.blur(out, (int(config.row_highpass_px), 1), borderType=cv2.BORDER_REFLECT)
    if config.column_highpass_px > 1:
        out = out - cv2.blur(out, (1, int(config.column_highpass_px)), borderType=cv2.BORDER_REFLECT)
    return out


def bandpass_margins(config: TrackerConfig) -> tuple[int, int]:
    """(rows, cols) of context the band-pass needs around a region for its values there to be those of
    the whole image (OpenCV's Gaussian reaches 4 sigma)."""
    blur = int(math.ceil(4 * config.lowpass_sigma_px)) + 1 if config.lowpass_sigma_px > 0 else 0
    return blur + int(config.column_highpass_px) // 2, blur + int(config.row_highpass_px) // 2


# --------------------------------------------------------------------------- kernels


@dataclass
class LarynxKernel:
    """normals [h,w,3] float32 camera-space normals of the larynx and its surroundings (what the raw
    correlation baseline matches); centre (x, y) the kernel-pixel coordinates of the larynx point;
    cm_per_px its scale if known; source a description.

    context [H',W',3] (optional): the image the kernel was cut from, the kernel's top-left pixel at
    ``offset`` (col, row); the band-pass then sees the same neighbourhood as in the frames (without it
    the kernel's borders are reflected).  background [H',W',3] (optional, with a context): the same view
    without the larynx (the rig rendered with eta = 0).  The matched template is then the larynx's own
    normal perturbation, bandpass(context) - bandpass(background), cut at the kernel: the neck around
    the larynx, which stays put while the larynx slides, is no longer part of what is matched (real
    HACK rig: tracked rise 0.95 of the truth against 0.89 matching the band-passed rest render itself,
    noisy 95th percentile error 1.24 px against 1.9; on the built-in rig's smooth neck the two match).
    """

    normals: np.ndarray
    centre: tuple[float, float]
    cm_per_px: float | None = None
    source: str = ""
    context: np.ndarray | None = None
    offset: tuple[int, int] = (0, 0)
    background: np.ndarray | None = None

    def __post_init__(self) -> None:
        self.normals = np.ascontiguousarray(self.normals, dtype=np.float32)
        self.centre = (float(self.centre[0]), float(self.centre[1]))
        self.offset = (int(self.offset[0]), int(self.offset[1]))
        for name in ("context", "background"):
            if getattr(self, name) is not None:
                setattr(self, name, np.ascontiguousarray(getattr(self, name), dtype=np.float32))
        if self.background is not None and (self.context is None or self.background.shape != self.context.shape):
            raise ValueError("a kernel's background must come with a context of the same shape")

    def template(self, config: TrackerConfig) -> np.ndarray:
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


def rig_kernel(rig, cm_per_px: float = DEFAULT_CM_PER_PX, size: int = KERNEL_SIZE, margin: int = 96) -> LarynxKernel:
    """The generic larynx kernel: the rig at rest (theta 0, psi 0, tau 0, eta 1) in the default neck view at
    ``cm_per_px``, ``size`` px square, centred on the larynx point (its centre is the middle pixel).  Its
    context is the view ``margin`` px wider on each side (``bandpass_margins``: enough for column high-passes
    up to 160 px), its background the same view without the larynx (eta 0), so that what is matched is the
    larynx's normal perturbation."""
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
    """A kernel image (.npy [h,w,3], .png, .exr; the frames' encoding), centred on its middle pixel."""
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
    """The kernel resampled to ``cm_per_px`` (a no-op when its own scale is unknown or equal)."""
    if kernel.cm_per_px is None or math.isclose(kernel.cm_per_px, cm_per_px, rel_tol=1e-6):
        return kernel
    factor = kernel.cm_per_px / cm_per_px
    w, h = kernel.size
    size = (max(3, round(w * factor)), max(3, round(h * factor)))

    def resample(image: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        out = cv2.resize(image, shape, interpolation=cv2.INTER_AREA if factor < 1 else cv2.INTER_LINEAR)
        norms = np.linalg.norm(out, axis=-1, keepdims=True)
        return np.where(norms > MIN_NORM, out / np.maximum(norms, 1e-6), 0.0).astype(np.float32)

    fx, fy = size[0] / w, size[1] / h  # continuous coordinates: x' = (x + 0.5) * f - 0.5
    source = f"{kernel.source} rescaled to {cm_per_px:g} cm/px"
    if kernel.context is None:
        centre = ((kernel.centre[0] + 0.5) * fx - 0.5, (kernel.centre[1] + 0.5) * fy - 0.5)
        return LarynxKernel(resample(kernel.normals, size), centre, cm_per_px, source)
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
                        background)


def rig_px_per_tau(rig, cm_per_px: float = DEFAULT_CM_PER_PX, delta: float = 0.02, perspective: bool = False) -> float:
    """Pixels of upward image motion of the larynx point per tau unit, in the default neck view at rest."""
    renderer = NeckRenderer(rig, neck_camera(rig, 64, cm_per_px, perspective))
    _, pixels = renderer.pose(rig.neutral(2), tau=torch.tensor([-delta, delta]))
    return float(pixels[0, 1] - pixels[1, 1]) / (2 * delta)


# --------------------------------------------------------------------------- matching


# Least squares fit of f = a + b x + c y + d x^2 + e x y + g y^2 to the 3x3 values around a maximum.
_OFFSETS = np.array([(dx, dy) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], dtype=np.float64)
_QUADRATIC_FIT = np.linalg.pinv(np.stack([np.ones(9), _OFFSETS[:, 0], _OFFSETS[:, 1], _OFFSETS[:, 0] ** 2,
                                          _OFFSETS[:, 0] * _OFFSETS[:, 1], _OFFSETS[:, 1] ** 2], axis=1))


def subpixel_peak(scores: np.ndarray, col: int, row: int) -> tuple[float, float]:
    """Sub-pixel (x, y) of the maximum at (col, row) of a score map: a 2-D quadratic through its 3x3
    neighbourhood (1-D parabolas along an axis where the fit is not a maximum or at the border)."""
    h, w = scores.shape
    if 0 < col < w - 1 and 0 < row < h - 1:
        a, b, c, d, e, g = _QUADRATIC_FIT @ scores[row - 1:row + 2, col - 1:col + 2].reshape(-1).astype(np.float64)
        det = 4 * d * g - e * e
        if d < 0 and det > 0:
            dx = (-2 * g * b + e * c) / det
            dy = (-2 * d * c + e * b) / det
            if abs(dx) <= 1 and abs(dy) <= 1:
                return col + dx, row + dy

    # (col, row) is the maximum, so each parabola's vertex is a maximum too (or the samples are flat: 0).
    dx = parabolic_peak(*scores[row, col - 1:col + 2])[0] if 0 < col < w - 1 else 0.0
    dy = parabolic_peak(*scores[row - 1:row + 2, col])[0] if 0 < row < h - 1 else 0.0
    return col + dx, row + dy


def match_window(kernel: LarynxKernel, config: TrackerConfig) -> np.ndarray | None:
    """The weight [h,w] float32 of each kernel pixel in the match: a Gaussian of sigmas
    (``window_sigma_x_px``, ``window_sigma_y_px``) around the kernel's centre; None (all pixels alike)
    when either sigma is 0.

    The larynx point is the centroid of the larynx's cap, the body of the larynx around the kernel's
    centre; the kernel's outer parts move otherwise.  Under head motion the larynx region shears (when
    the neck flexes its top moves 2.5-4 times as far as its bottom, on both rigs), and on the real HACK
    rig the top of the larynx squeezes into the jaw corner as it rises.  Unweighted, the match follows
    the larynx's lower flanks: under flexion it moves 0.70 times as far as the larynx point on the
    built-in rig (0.83 weighted), the real rig's rise is 0.87 (0.95 weighted), and on noisy sequences
    the median / 95th percentile error is 0.35 / 0.63 px instead of 0.24 / 0.56 (built-in) and
    0.67 / 2.3 px instead of 0.43 / 1.24 (real rig).
    """
    sigma_x, sigma_y = config.window_sigma_x_px, config.window_sigma_y_px
    if sigma_x <= 0 or sigma_y <= 0:
        return None
    w, h = kernel.size
    rows, cols = np.mgrid[0:h, 0:w]
    dx, dy = (cols - kernel.centre[0]) / sigma_x, (rows - kernel.centre[1]) / sigma_y
    return np.exp(-0.5 * (dx * dx + dy * dy)).astype(np.float32)


@dataclass
class Match:
    """One frame's result: (x, y) pixels, peak NCC, accepted or held."""

    x: float
    y: float
    score: float
    accepted: bool


class LarynxTracker:
    """Frame-by-frame matcher of a LarynxKernel (see the module doc).  ``update(normals [H,W,3]) -> Match``."""

    def __init__(self, kernel: LarynxKernel, config: TrackerConfig | None = None,
                 init: tuple[float, float] | None = None):
        self.kernel = kernel
        self.config = config or TrackerConfig()
        self.template = kernel.template(self.config)
        self.weights = match_window(kernel, self.config)
        self.last = init              # last accepted (x, y)
        self.velocity = (0.0, 0.0)    # px per frame between the last two accepted positions
        self.missed = 0               # frames since the last accepted one

    def search(self, normals: np.ndarray, around: tuple[float, float] | None) -> tuple[float, float, float, bool]:
        """Best (x, y, score, inside) within the band around ``around`` (the whole frame if None); ``inside``
        is False when the best score lies on the band's border (the true peak may lie beyond it)."""
        kw, kh = self.kernel.size
        h, w = normals.shape[:2]
        cx, cy = self.kernel.centre
        if around is None:
            x0, y0, x1, y1 = 0, 0, w - kw, h - kh
        else:
            # Top-left corners of the kernel whose centre lies within the band.
            tx, ty = int(round(around[0] - cx)), int(round(around[1] - cy))
            x0, x1 = max(0, tx - self.config.band_cols), min(w - kw, tx + self.config.band_cols)
            y0, y1 = max(0, ty - self.config.band_rows), min(h - kh, ty + self.config.band_rows)
            if x1 < x0 or y1 < y0:
                return float("nan"), float("nan"), -1.0, False
        # Band-pass the window with the context the filters need, so it holds what filtering the whole
        # frame would give there.
        margin_rows, margin_cols = bandpass_margins(self.config)
        ya, yb = max(0, y0 - margin_rows), min(h, y1 + kh + margin_rows)
        xa, xb = max(0, x0 - margin_cols), min(w, x1 + kw + margin_cols)
        region = bandpass(normals[ya:yb, xa:xb], self.config)
        window = np.ascontiguousarray(region[y0 - ya:y1 + kh - ya, x0 - xa:x1 + kw - xa])
        scores = cv2.matchTemplate(window, self.template, cv2.TM_CCORR_NORMED, mask=self.weights)
        _, peak, _, (col, row) = cv2.minMaxLoc(scores)
        rows, cols = scores.shape
        inside = (0 < row < rows - 1 or rows == 1) and (0 < col < cols - 1 or cols == 1)
        if self.config.subpixel:
            px, py = subpixel_peak(scores, col, row)
        else:
            px, py = float(col), float(row)
        return x0 + px + cx, y0 + py + cy, float(peak), inside

    def prediction(self) -> tuple[float, float] | None:
        """Where the larynx should be in the next frame: the last accepted position moved on at the velocity
        between the last two accepted ones (constant velocity)."""
        if self.last is None:
            return None
        steps = self.missed + 1
        return self.last[0] + self.velocity[0] * steps, self.last[1] + self.velocity[1] * steps

    def update(self, normals: np.ndarray) -> Match:
        cfg = self.config
        reacquire = self.last is None or self.missed >= cfg.reacquire_after
        predicted = self.prediction()
        x, y, score, inside = self.search(normals, None if reacquire else predicted)
        ok = inside and score >= cfg.min_confidence
        if ok and not reacquire:
            ok = math.hypot(x - predicted[0], y - predicted[1]) <= cfg.max_jump_px * (self.missed + 1)
        if ok:
            if self.last is not None and not reacquire:
                steps = self.missed + 1
                self.velocity = ((x - self.last[0]) / steps, (y - self.last[1]) / steps)
            else:
                self.velocity = (0.0, 0.0)
            self.last, self.missed = (x, y), 0
            return Match(x, y, score, True)
        self.missed += 1
        held = self.last if self.last is not None else (float("nan"), float("nan"))
        return Match(held[0], held[1], score, False)


@dataclass
class Track:
    """Per-frame results: x, y [T] pixels, confidence [T] (0 where rejected), accepted [T] bool."""

    x: np.ndarray
    y: np.ndarray
    confidence: np.ndarray
    accepted: np.ndarray

    def __len__(self) -> int:
        return len(self.x)


def smooth_track(track: Track, sigma_frames: float) -> Track:
    """Confidence-weighted Gaussian smoothing of x and y (normalised convolution); rejected frames
    (confidence 0) take their neighbours' values."""
    if sigma_frames <= 0:
        return track
    weights = np.where(np.isfinite(track.x), track.confidence, 0.0).astype(np.float64)
    den = gaussian_filter1d(weights, sigma_frames, mode="constant", truncate=3.0)

    def smooth(values: np.ndarray) -> np.ndarray:
        num = gaussian_filter1d(np.nan_to_num(values) * weights, sigma_frames, mode="constant", truncate=3.0)
        return np.where(den > 1e-9, num / np.maximum(den, 1e-9), values)

    return Track(smooth(track.x), smooth(track.y), track.confidence, track.accepted)


def track_frames(frames: Iterable[np.ndarray], kernel: LarynxKernel, config: TrackerConfig | None = None,
                 init: tuple[float, float] | None = None, progress: bool = False, total: int | None = None) -> Track:
    """Track the kernel through decoded normal maps [H,W,3] (float32); smoothing per ``config``."""
    tracker = LarynxTracker(kernel, config, init)
    matches = []
    iterator = frames
    if progress:
        from tqdm import tqdm

        iterator = tqdm(frames, total=total, unit="frame", desc="tracking")
    for normals in iterator:
        matches.append(tracker.update(normals))
    if not matches:
        raise InputError("no frames to track")
    track = Track(np.array([m.x for m in matches]), np.array([m.y for m in matches]),
                  np.array([np.clip(m.score, 0.0, 1.0) if m.accepted else 0.0 for m in matches]),
                  np.array([m.accepted for m in matches]))
    return smooth_track(track, tracker.config.smooth_frames)


def raw_correlation_argmax(normals: np.ndarray, kernel: LarynxKernel) -> tuple[float, float]:
    """The plain estimate: integer arg-max over the whole frame of the raw correlation k * N (TM_CCORR)."""
    scores = cv2.matchTemplate(np.asarray(normals, np.float32), kernel.normals, cv2.TM_CCORR)
    _, _, _, (col, row) = cv2.minMaxLoc(scores)
    return col + kernel.centre[0], row + kernel.centre[1]


def track_columns(track: Track, fps: float, rest_frame: int = 0, px_per_tau: float | None = None) -> dict:
    """The CSV columns ``frame,time,x_px,y_px,tau_px,tau,confidence`` (tau NaN without calibration)."""
    if not 0 <= rest_frame < len(track):
        raise InputError(f"rest_frame={rest_frame}: expected a frame index in [0, {len(track) - 1}]")
    if not np.isfinite(track.y[rest_frame]):
        raise InputError(f"rest_frame={rest_frame}: the larynx was not found in that frame; choose another")
    tau_px = track.y[rest_frame] - track.y
    tau = tau_px / px_per_tau if px_per_tau else np.full(len(track), np.nan)
    return {"frame": np.arange(len(track)), "time": np.arange(len(track)) / fps, "x_px": track.x, "y_px": track.y,
            "tau_px": tau_px, "tau": tau, "confidence": track.confidence}


def plot_track(path: str | Path, columns: dict, accepted: np.ndarray, px_per_tau: float | None = None,
               title: str = "") -> None:
    """tau_px (and tau, with a calibration ``px_per_tau``) over time, the rejected frames (``accepted`` [T]
    False) marked, and the confidence, as a PNG (atomic).  ``columns``: :func:`track_columns`."""
    time = columns["time"]
    fig, (top, bottom) = figure(nrows=2, ncols=1, figsize=(9, 5), sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    top.plot(time, columns["tau_px"], color="tab:blue", lw=1.2)
    top.set_ylabel("larynx rise tau_px (px, + = up)")
    if px_per_tau:
        right = top.secondary_yaxis("right", functions=(lambda p: p / px_per_tau, lambda t: t * px_per_tau))
        right.set_ylabel("tau (UV units)")
    rejected = ~np.asarray(accepted, dtype=bool)
    if rejected.any():
        top.plot(time[rejected], columns["tau_px"][rejected], "x", color="tab:red", ms=4, label="rejected (held)")
        top.legend(loc="upper right")
    top.set_title(title)
    top.grid(alpha=0.3)
    bottom.plot(time, columns["confidence"], color="tab:green", lw=1.0)
    bottom.set_ylim(0, 1.02)
    bottom.set_ylabel("confidence")
    bottom.set_xlabel("time (s)")
    bottom.grid(alpha=0.3)
    save_figure(fig, path, dpi=100)


# --------------------------------------------------------------------------- CLI


def tracker_config_from(cfg) -> TrackerConfig:
    """TrackerConfig from the ``tracker`` section, scaled to ``cm_per_px`` when given."""
    config = config_dataclass(TrackerConfig, cfg.tracker, "tracker (configs/track.yaml)")
    return config.at_scale(float(cfg.cm_per_px)) if cfg.get("cm_per_px") is not None else config


def build_kernel(cfg, first_frame: np.ndarray, first_label: str, rig_loader) -> LarynxKernel:
    """The kernel the config asks for (``kernel=rig|frame|<file>``), at the capture's scale."""
    size = int(cfg.kernel_size)
    cm_per_px = float(cfg.cm_per_px) if cfg.cm_per_px is not None else None
    if cfg.kernel == "rig":
        kernel = rig_kernel(rig_loader(), cm_per_px or DEFAULT_CM_PER_PX, size)
    elif cfg.kernel == "frame":
        if cfg.init_x is None or cfg.init_y is None:
            raise InputError("kernel=frame cuts the kernel from the first frame: give init_x=... init_y=... "
                             "(the larynx's pixel position in it)")
        return kernel_from_frame(first_frame, float(cfg.init_x), float(cfg.init_y), size, first_label, cm_per_px)
    else:
        own = float(cfg.kernel_cm_per_px) if cfg.kernel_cm_per_px is not None else None
        kernel = kernel_from_file(cfg.kernel, own, str(cfg.float_encoding))
    return rescale_kernel(kernel, cm_per_px) if cm_per_px else kernel


def run(cfg) -> dict:
    """The CLI's work for a composed ``configs/track.yaml`` (tests call this in-process); returns the columns."""
    cv2.setNumThreads(int(cfg.threads))  # torch's are set by data.cli.run_cli
    started = _time.perf_counter()
    source = open_source(cfg.input, cfg.fps, str(cfg.float_encoding))
    rig_cache: list = []

    def rig_loader():
        if not rig_cache:
            from models.rig import HeadNeckModel

            rig_cache.append(HeadNeckModel.from_config(cfg.rig))
        return rig_cache[0]

    frames = source.frames()
    head = next(frames, None)
    if head is None:
        raise InputError(f"{cfg.input}: no frames; expected at least one normal map")
    _, first_label, first = head
    kernel = build_kernel(cfg, first, first_label, rig_loader)
    h, w = first.shape[:2]
    if kernel.size[0] > w or kernel.size[1] > h:
        raise InputError(f"{first_label}: the {kernel.size[0]}x{kernel.size[1]} kernel is larger than the "
                         f"{w}x{h} frames; give cm_per_px= (the capture's scale) or a smaller kernel_size")
    init = None
    if cfg.init_x is not None and cfg.init_y is not None:
        init = (float(cfg.init_x), float(cfg.init_y))

    def all_frames():
        yield first
        for _, _, normals in frames:
            yield normals

    track = track_frames(all_frames(), kernel, tracker_config_from(cfg), init, progress=bool(cfg.progress),
                         total=source.count)
    px_per_tau = cfg.px_per_tau
    if px_per_tau == "auto":
        px_per_tau = (rig_px_per_tau(rig_loader(), float(cfg.cm_per_px or DEFAULT_CM_PER_PX))
                      if cfg.kernel == "rig" else None)
    elif px_per_tau is not None:
        try:
            px_per_tau = float(px_per_tau)
        except ValueError:
            raise InputError(f"px_per_tau={px_per_tau}: expected auto, a number or null") from None
    columns = track_columns(track, source.fps, int(cfg.rest_frame), px_per_tau)
    write_csv(cfg.out, columns, float_format="%.9g")  # time of an hour-long take to 1e-5 s
    plot = cfg.plot if cfg.plot != "auto" else str(Path(cfg.out).with_suffix(".png"))
    if plot:
        plot_track(plot, columns, track.accepted, px_per_tau, f"{Path(str(cfg.input)).name}: kernel {kernel.source}")
    elapsed = _time.perf_counter() - started
    rejected = int((~track.accepted).sum())
    calibration = f"{px_per_tau:.1f} px per tau unit" if px_per_tau else "no calibration (tau column NaN)"
    print(f"tracked {len(track)} frames at {source.fps:g} fps in {elapsed:.1f} s; {rejected} rejected; "
          f"median confidence {np.median(track.confidence):.3f}; {calibration}; wrote {cfg.out}"
          + (f" and {plot}" if plot else ""))
    return columns


if __name__ == "__main__":
    run_cli("track", run)
