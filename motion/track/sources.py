"""Normal-map frames for the tracker: decoding, validation and the sources (image folders, videos, stacks).

Input (:func:`open_source`): a folder of images (8/16-bit PNG or TIFF, float EXR; sorted by name,
numbers compared as numbers), a video file (anything ``cv2.VideoCapture`` reads), or a ``.npy`` stack
``[T,H,W,3]``.  The encoding is ``data.normals``'s: RGB = (n + 1) / 2 of camera-space unit normals,
scaled to the integer range of 8/16-bit images and videos.  Float data (EXR, float ``.npy``) is read
with ``float_encoding``: ``raw`` = the normals themselves in [-1, 1], ``encoded`` = (n + 1) / 2 in
[0, 1], ``auto`` (default) = raw if the first frame has a negative value, else encoded.  ``.npy``
stacks of uint8 / uint16 are encoded.

Background: pixels whose decoded vector is shorter than 0.5 (e.g. grey) or longer than 1.5 (black
decodes to (-1, -1, -1)); they count as n = 0.  Validation: every frame must have at least 2 %
foreground, and at least 80 % of its foreground (checked on every 4th pixel) must decode to vectors of
norm 1 +- 0.15; otherwise ``InputError`` names the file or frame.

Frame rate: the video's own (``CAP_PROP_FPS``) unless ``fps`` is given; ``fps`` (default 30) for image
folders and ``.npy`` stacks.
"""
from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from base.errors import InputError
from data.normals import FLOAT_IMAGE_SUFFIXES, INTEGER_IMAGE_SUFFIXES, decode_normals, read_normal_image, stored_to_unit
from motion.face.frames import VIDEO_SUFFIXES

DEFAULT_FPS = 30.0               # image folders and .npy stacks carry no frame rate
MIN_NORM = 0.5                   # decoded vectors shorter than this (grey) are background
MAX_NORM = 1.5                   # ... and longer than this (black decodes to (-1,-1,-1), length 1.73)
UNIT_TOLERANCE = 0.15            # | |n| - 1 | allowed for a foreground pixel to count as a normal
MIN_UNIT_FRACTION = 0.8          # share of foreground pixels that must be unit normals
MIN_FOREGROUND = 0.02            # share of the frame that must be foreground
FLOAT_ENCODINGS = ("auto", "raw", "encoded")


def float_is_raw(values: np.ndarray, float_encoding: str) -> bool:
    """Whether float data ``values`` holds raw normals in [-1, 1] (else the encoding (n + 1) / 2):
    ``float_encoding`` raw / encoded, or auto = raw if any value is negative."""
    if float_encoding == "auto":
        return bool(values.min() < 0)
    return float_encoding == "raw"


def decode_frame(rgb: np.ndarray, is_raw: bool) -> np.ndarray:
    """Stored values [H,W,3] (raw normals, or the encoding in [0, 1]) -> camera-space normals float32
    [H,W,3], background (see the module doc) 0."""
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


def video_properties(path: Path) -> tuple[float, int]:
    """(frame rate as the container reports it, 0 when it reports none; frame count) of a video file;
    InputError when OpenCV cannot open it."""
    capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise InputError(f"{path}: OpenCV cannot open this video")
        rate = capture.get(cv2.CAP_PROP_FPS)
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
        return (float(rate) if rate and rate > 0 and np.isfinite(rate) else 0.0), count
    finally:
        capture.release()


def open_source(path: str | Path, fps: float | None = None, float_encoding: str = "auto") -> NormalMapSource:
    """A folder of images, a video file or a .npy stack [T,H,W,3] (see the module doc for the encoding).

    Args:
        path: the folder, video or stack.
        fps: the frame rate; None = the video's own, or 30 for folders and stacks.
        float_encoding: auto, raw or encoded (float data only).
    Returns:
        the source; InputError names what is wrong with the input.
    """
    path = Path(path)
    if float_encoding not in FLOAT_ENCODINGS:
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
        video_fps, count = video_properties(path)
        rate = fps or video_fps
        if not rate:
            raise InputError(f"{path}: the video reports no frame rate; give fps=...")
        return NormalMapSource(path, "video", float(rate), count, float_encoding)
    raise InputError(f"{path}: unsupported input '{path.suffix}'; expected a folder of images, a video "
                     f"({', '.join(VIDEO_SUFFIXES)}) or a .npy stack")
