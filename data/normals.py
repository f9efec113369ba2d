"""Normal maps: the one RGB encoding of camera-space normals, and normal-map image files.

Conventions owned here (the renderer ``scene.render``, the tracker ``motion.track`` and the sequence
generator ``scene.normal_sequences`` use them):

- RGB encoding of a normal map: ``rgb = (n + 1) / 2`` per channel (R = n_x,
  G = n_y, B = n_z), so [-1, 1] -> [0, 1]; background pixels (mask false)
  hold n = 0 and are written black (rgb 0).
- Camera space: x right, y up, z towards the camera (``scene.render`` owns the camera).
- On disk a normal map is an RGB image: PNG (8 or 16 bit, also TIFF) holding the encoding (n + 1) / 2
  scaled to the integer range, background black; or EXR holding float32 raw normals n in [-1, 1],
  background 0.  EXR goes through the OpenEXR package (a dependency: the OpenCV wheels cannot read EXR).
  EXR files of other tools are read too: R, G, B as separate channels or as one layer's
  ``<layer>.R/G/B``, half or full floats, an alpha channel ignored; their values are the caller's to
  interpret (raw or encoded: ``motion.track``'s ``float_encoding``).
"""
from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from base.errors import InputError, require_file
from base.files import atomic_path


def encode_normals(normals):
    """Camera-space normals [..., 3] in [-1,1] (numpy or torch) -> RGB in [0,1]: (n + 1) / 2; zero
    vectors (background) -> black."""
    foreground = ~(normals == 0).all(-1)[..., None]
    return (normals + 1.0) / 2.0 * foreground


def decode_normals(rgb):
    """RGB [..., 3] in [0,1] (numpy or torch) -> normals 2 * rgb - 1 (not renormalised; what counts as
    background when decoding frames: ``motion.track.sources.decode_frame``)."""
    return rgb * 2.0 - 1.0


# ----------------------------------------------------------------------------- normal-map image files

INTEGER_IMAGE_SUFFIXES = (".png", ".tif", ".tiff")
FLOAT_IMAGE_SUFFIXES = (".exr",)


def write_normal_image(path: str | os.PathLike, normals: np.ndarray, bit_depth: int = 8) -> None:
    """Write camera-space normals [H,W,3] (0 = background) atomically: PNG/TIFF encoded at ``bit_depth``
    (8 or 16) bits, EXR as float32 raw normals."""
    path = Path(path)
    normals = np.asarray(normals, dtype=np.float32)
    suffix = path.suffix.lower()
    with atomic_path(path) as tmp:
        if suffix in FLOAT_IMAGE_SUFFIXES:
            import OpenEXR

            header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
            with OpenEXR.File(header, {"RGB": np.ascontiguousarray(normals)}) as exr:
                exr.write(str(tmp))
        elif suffix in INTEGER_IMAGE_SUFFIXES:
            if bit_depth not in (8, 16):
                raise ValueError(f"bit_depth {bit_depth}: expected 8 or 16")
            top = 255 if bit_depth == 8 else 65535
            encoded = np.rint(encode_normals(normals) * top).astype(np.uint8 if bit_depth == 8 else np.uint16)
            if not cv2.imwrite(str(tmp), np.ascontiguousarray(encoded[..., ::-1])):
                raise OSError(f"{path}: OpenCV could not write the image")
        else:
            raise ValueError(f"{path}: unsupported normal-map format '{path.suffix}', expected .png, .tif or .exr")


def stored_to_unit(values: np.ndarray, label: str = "image", dtype=np.float32) -> tuple[np.ndarray, bool]:
    """Stored pixel values [...] -> (values as ``dtype``, is_float).

    Unsigned integers (8/16-bit images and videos, integer ``.npy`` stacks) are divided by their type's
    maximum, so [0, 255] or [0, 65535] -> [0, 1]; floats come back as stored (their meaning, raw or
    encoded, is the caller's).  Other types raise InputError naming ``label``.
    """
    values = np.asarray(values)
    if values.dtype.kind == "f":
        return values.astype(dtype, copy=False), True
    if values.dtype.kind == "u":
        return values.astype(dtype) / float(np.iinfo(values.dtype).max), False
    raise InputError(f"{label}: pixel type {values.dtype}, expected unsigned integers (8/16-bit) or floats")


def _exr_rgb(channels: dict, path: Path) -> np.ndarray:
    """R, G, B [H,W,3] float32 from an EXR's channels read one by one (``separate_channels``): the channels
    ``R, G, B`` or those of one layer ``<layer>.R, <layer>.G, <layer>.B`` (as compositing tools name them)."""
    names = sorted(channels)
    layers = sorted({n[:-2] for n in names if n.endswith((".R", ".G", ".B"))
                     and all(f"{n[:-2]}.{c}" in channels for c in "RGB")})
    if all(c in channels for c in "RGB"):
        keys = ["R", "G", "B"]
    elif len(layers) == 1:
        keys = [f"{layers[0]}.{c}" for c in "RGB"]
    else:
        found = ", ".join(names[:8]) + (" ..." if len(names) > 8 else "")
        detail = f"layers {', '.join(layers)}: give a file with one" if layers else f"channels {found}"
        raise InputError(f"{path}: EXR {detail}; expected R, G, B channels (a normal map)")
    return np.stack([np.asarray(channels[k].pixels, dtype=np.float32) for k in keys], axis=-1)


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    try:
        with OpenEXR.File(str(path), separate_channels=True) as exr:
            rgb = _exr_rgb(exr.channels(), path)
    except InputError:
        raise
    except Exception as e:  # the binding raises plain exceptions on bad files
        raise InputError(f"{path}: not a readable EXR image ({e})") from None
    if rgb.ndim != 3:
        raise InputError(f"{path}: EXR channels of shape {rgb.shape[:-1]}, expected images [H,W]")
    return rgb


def read_normal_image(path: str | os.PathLike) -> tuple[np.ndarray, bool]:
    """Read one normal-map image as stored: (rgb [H,W,3] float32, is_float).

    Integer images (8/16-bit PNG/TIFF) come back divided by their integer maximum, so in [0, 1] (the
    encoding); float images (EXR, float TIFF) come back as stored (:func:`stored_to_unit`).  An alpha
    channel is dropped.
    """
    path = require_file(path)
    suffix = path.suffix.lower()
    if suffix in FLOAT_IMAGE_SUFFIXES:
        return _read_exr(path), True
    if suffix not in INTEGER_IMAGE_SUFFIXES:
        raise InputError(f"{path}: unsupported image format '{path.suffix}', expected .png, .tif/.tiff or .exr")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError(f"{path}: not a readable image")
    if image.ndim != 3 or image.shape[2] < 3:
        raise InputError(f"{path}: image of shape {image.shape}, expected an RGB normal map (3 channels)")
    return stored_to_unit(image[..., 2::-1], str(path))
