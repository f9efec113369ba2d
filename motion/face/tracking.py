"""MediaPipe FaceLandmarker over the frames of a video: per frame, whether a face was found, its ARKit
blendshape weights and its head rotation.

Blendshapes: MediaPipe's 52 categories are ARKit's blendshape names in camelCase (``eyeBlinkLeft``,
``jawOpen``, ...) plus ``_neutral``, without ``tongueOut``; they are kept by name (:data:`ARKIT_NAMES` is
the order of the arrays here), so a model that orders or names a few differently still maps by name.
Left and right are the subject's, as in ARKit (measured on the rendered ICT head, tests/test_face_video.py).

Head rotation: the facial transformation matrix [4,4] maps MediaPipe's canonical face model (cm; x to the
face's own left, y up, z out of the face) into its camera frame (OpenGL's: x to the image's right, y up,
z towards the viewer; the camera looks along -z).  A subject facing the camera has the face's left on the
image's right, so both frames are the rig's world frame (``motion.head2neck``: x to the subject's left, y
up, face towards +z) and the rotation block, orthonormalised (SVD: the nearest rotation), is directly a
head orientation of the ``matrix`` convention, identity when facing the camera.  Checked on renders of
the ICT head turned by known yaw, pitch and roll (tests/test_face_video.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from base.progress import progress_bar
from motion.face.frames import VideoFrames

ARKIT_NAMES: tuple[str, ...] = (
    "_neutral", "browDownLeft", "browDownRight", "browInnerUp", "browOuterUpLeft", "browOuterUpRight",
    "cheekPuff", "cheekSquintLeft", "cheekSquintRight", "eyeBlinkLeft", "eyeBlinkRight", "eyeLookDownLeft",
    "eyeLookDownRight", "eyeLookInLeft", "eyeLookInRight", "eyeLookOutLeft", "eyeLookOutRight", "eyeLookUpLeft",
    "eyeLookUpRight", "eyeSquintLeft", "eyeSquintRight", "eyeWideLeft", "eyeWideRight", "jawForward", "jawLeft",
    "jawOpen", "jawRight", "mouthClose", "mouthDimpleLeft", "mouthDimpleRight", "mouthFrownLeft",
    "mouthFrownRight", "mouthFunnel", "mouthLeft", "mouthLowerDownLeft", "mouthLowerDownRight", "mouthPressLeft",
    "mouthPressRight", "mouthPucker", "mouthRight", "mouthRollLower", "mouthRollUpper", "mouthShrugLower",
    "mouthShrugUpper", "mouthSmileLeft", "mouthSmileRight", "mouthStretchLeft", "mouthStretchRight",
    "mouthUpperUpLeft", "mouthUpperUpRight", "noseSneerLeft", "noseSneerRight",
)
_INDEX = {name.lower(): k for k, name in enumerate(ARKIT_NAMES)}


@dataclass
class FaceSamples:
    """What the landmarker saw, one row per video frame.

    time [T] s from the first frame; found [T] bool; weights [T,52] float32 in :data:`ARKIT_NAMES` order
    (0 where no face); rotation [T,3,3] float64 head orientations in the rig's world frame (identity where
    no face); translation [T,3] cm, the face's origin in the camera frame (0 where no face).
    """

    time: np.ndarray
    found: np.ndarray
    weights: np.ndarray
    rotation: np.ndarray
    translation: np.ndarray

    def __len__(self) -> int:
        return len(self.time)


def nearest_rotation(matrix: np.ndarray) -> np.ndarray:
    """The rotation nearest (Frobenius) to ``matrix`` [...,3,3]: U V^T of its SVD, det +1."""
    u, _, vt = np.linalg.svd(matrix)
    d = np.sign(np.linalg.det(u @ vt))
    return u @ (vt * np.stack([np.ones_like(d), np.ones_like(d), d], -1)[..., :, None])


def head_ypr(rotation: np.ndarray) -> np.ndarray:
    """Yaw, pitch, roll [...,3] (radians) of head orientations [...,3,3]: the inverse of
    ``base.rotations.ypr_to_matrix`` (R = Ry(yaw) Rx(pitch) Rz(roll); |pitch| < 90 deg), for what takes angles
    (the live stream's HeadYaw, HeadPitch, HeadRoll)."""
    r = np.asarray(rotation, dtype=np.float64)
    return np.stack([np.arctan2(r[..., 0, 2], r[..., 2, 2]), np.arcsin(-np.clip(r[..., 1, 2], -1.0, 1.0)),
                     np.arctan2(r[..., 1, 0], r[..., 1, 1])], axis=-1)


def detect(landmarker, rgb: np.ndarray, milliseconds: int) -> tuple[np.ndarray, np.ndarray] | None:
    """(ARKit weights [52], facial transformation matrix [4,4]) of the face in ``rgb`` uint8 [H,W,3] at
    ``milliseconds`` (increasing between calls: VIDEO mode), or None when no face is found."""
    import mediapipe as mp

    image = mp.Image(image_format=mp.ImageFormat.SRGB, data=np.ascontiguousarray(rgb))
    result = landmarker.detect_for_video(image, int(milliseconds))
    if not result.face_blendshapes or not result.facial_transformation_matrixes:
        return None
    weights = np.zeros(len(ARKIT_NAMES), dtype=np.float32)
    for category in result.face_blendshapes[0]:
        k = _INDEX.get(category.category_name.lower())
        if k is not None:
            weights[k] = category.score
    return weights, np.asarray(result.facial_transformation_matrixes[0], dtype=np.float64)


def track_faces(video: VideoFrames, landmarker, show_progress: bool = True) -> FaceSamples:
    """Run ``landmarker`` (``motion.face.model.open_landmarker``) over every frame of ``video``."""
    times, found, weights, matrices = [], [], [], []
    progress = progress_bar(total=video.count, desc=f"{video.path.name}: faces", unit="frame",
                            disable=not show_progress)
    last_ms = -1
    for _, seconds, rgb in video.frames():
        milliseconds = max(int(round(seconds * 1000.0)), last_ms + 1)  # VIDEO mode: strictly increasing
        last_ms = milliseconds
        face = detect(landmarker, rgb, milliseconds)
        times.append(seconds)
        found.append(face is not None)
        weights.append(face[0] if face else np.zeros(len(ARKIT_NAMES), dtype=np.float32))
        matrices.append(face[1] if face else np.eye(4))
        progress.update(1)
    progress.close()
    matrices = np.stack(matrices)
    return FaceSamples(np.asarray(times), np.asarray(found, dtype=bool), np.stack(weights),
                       nearest_rotation(matrices[:, :3, :3]), matrices[:, :3, 3].copy())
