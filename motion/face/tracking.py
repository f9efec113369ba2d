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
up, face towards +z) and the rotation block, orthonormalised (the nearest rotation), is directly a
head orientation of the ``matrix`` convention, identity when facing the camera.  Checked on renders of
the ICT head turned by known yaw, pitch and roll (tests/test_face_video.py).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from base.progress import progress_bar
from base.rotations import nearest_rotation_np
from data.expressions import EXPRESSION_NAMES, arkit_name
from motion.face.frames import VideoFrames

# MediaPipe's categories: the ARKit names HACK's expressions map from (``data.expressions.arkit_name``) and
# ``_neutral``, sorted as MediaPipe lists them.
ARKIT_NAMES: tuple[str, ...] = ("_neutral", *sorted({arkit_name(n) for n in EXPRESSION_NAMES} - {None}))
ARKIT_INDEX = {name.lower(): k for k, name in enumerate(ARKIT_NAMES)}  # lower-case name -> column


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
        k = ARKIT_INDEX.get(category.category_name.lower())
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
                       nearest_rotation_np(matrices[:, :3, :3]), matrices[:, :3, 3].copy())
