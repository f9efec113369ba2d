"""A face video as an expression recording: ``read_face_video(path) -> ExpressionTrack``.

The video (:mod:`motion.face.frames`) goes through MediaPipe's FaceLandmarker (:mod:`motion.face.model`,
:mod:`motion.face.tracking`), and the result becomes a ``data.expressions.ExpressionTrack`` on the video's
own timestamps:

- ``psi`` [T,55]: the ARKit weights mapped by name to the HACK expressions as the CSV reader maps ARKit
  columns (``data.expressions.arkit_name``: ``browInnerUp`` and ``cheekPuff`` drive both sides);
  ``cheekRaiser_L/R`` have no ARKit counterpart and are listed in ``missing`` (left at 0);
- ``head_rotation`` [T,3,3]: the head's orientation in the rig's world frame (``motion.head2neck``'s
  ``matrix`` input; the axis conversion in :mod:`motion.face.tracking`);
- ``tracked`` [T] bool: the frames where a face was found.

Frames without a face are filled in: weights linearly between the neighbouring found frames (held at the
ends), rotations by normalised quaternion interpolation.  Gaps longer than ``max_gap`` seconds are
reported (``announce``) with their times; a video with no face at all is an InputError naming the file.
``smoothing``: the causal One Euro filter of :mod:`motion.face.smoothing` on weights and rotation.
Mirrored (selfie) footage: ``ExpressionTrack.mirrored()`` (``mirror=true`` in ``python infer.py``).
"""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from base.errors import InputError
from base.files import write_csv
from base.rotations import quaternion_to_matrix
from data.expressions import EXPRESSION_NAMES, ExpressionTrack, arkit_name
from motion.face.frames import open_video
from motion.face.model import find_face_model, open_landmarker, require_mediapipe
from motion.face.smoothing import ROTATION_FILTER, WEIGHT_FILTER, continuous_quaternions, smooth_rotations
from motion.face.tracking import ARKIT_INDEX, FaceSamples, track_faces

DEFAULT_MAX_GAP = 0.5   # s: a face lost for longer is reported (a blink of tracking is not)


def hack_weights(arkit: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """ARKit weights [T,52] (``ARKIT_NAMES`` order) -> HACK psi [T,55] float32 and the HACK names without an
    ARKit source (left at 0)."""
    psi = np.zeros((len(arkit), len(EXPRESSION_NAMES)), dtype=np.float32)
    missing = []
    for k, name in enumerate(EXPRESSION_NAMES):
        source = arkit_name(name)
        if source is None or source.lower() not in ARKIT_INDEX:
            missing.append(name)
            continue
        psi[:, k] = arkit[:, ARKIT_INDEX[source.lower()]]
    return psi, missing


def gaps(found: np.ndarray) -> list[tuple[int, int]]:
    """Runs of frames without a face as (first, last) frame indices, inclusive."""
    edges = np.diff(np.concatenate([[0], (~found).astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1) - 1))


def fill_gaps(samples: FaceSamples) -> tuple[np.ndarray, np.ndarray]:
    """(weights [T,52], rotations [T,3,3]) with the frames without a face interpolated between the found
    ones (linear; rotations as continuous quaternions, renormalised), held constant before the first and
    after the last found frame."""
    found = samples.found
    weights, rotation = samples.weights.copy(), samples.rotation.copy()
    if found.all():
        return weights, rotation
    time, seen = samples.time, np.flatnonzero(found)
    for k in range(weights.shape[1]):
        weights[:, k] = np.interp(time, time[seen], samples.weights[seen, k])
    quaternions = continuous_quaternions(samples.rotation[seen])
    filled = np.stack([np.interp(time, time[seen], quaternions[:, k]) for k in range(4)], axis=1)
    filled /= np.linalg.norm(filled, axis=1, keepdims=True)
    return weights, quaternion_to_matrix(torch.as_tensor(filled)).numpy()


def describe_gaps(samples: FaceSamples, max_gap: float) -> list[str]:
    """One phrase per gap longer than ``max_gap`` seconds: its times and frames."""
    period = float(np.median(np.diff(samples.time))) if len(samples) > 1 else 0.0
    phrases = []
    for first, last in gaps(samples.found):
        start = samples.time[first]
        stop = samples.time[last] + period
        if stop - start > max_gap:
            phrases.append(f"{start:.2f}-{stop:.2f} s (frames {first}-{last})")
    return phrases


def read_face_video(path: str | Path, face_model: str | None = None, smoothing: bool = False,
                    max_gap: float = DEFAULT_MAX_GAP, show_progress: bool = True, announce=print) -> ExpressionTrack:
    """The face in the video at ``path`` as an ExpressionTrack (see the module docstring)."""
    video = open_video(path)           # a bad file fails here, before the model loads
    require_mediapipe()
    landmarker = open_landmarker(find_face_model(face_model))
    try:
        samples = track_faces(video, landmarker, show_progress)
    finally:
        landmarker.close()
    if not samples.found.any():
        raise InputError(f"{video.path}: no face found in any of its {len(samples)} frames; expected a video of a "
                         f"face (frontal or turned, lit, at least about 100 pixels across)")
    long_gaps = describe_gaps(samples, max_gap)
    if long_gaps:
        announce(f"{video.path}: no face for more than {max_gap:g} s at {', '.join(long_gaps)}; filled in "
                 f"by interpolation (face_frames.csv lists every frame)")
    weights, rotation = fill_gaps(samples)
    if smoothing:
        weights = WEIGHT_FILTER(samples.time, weights)
        rotation = smooth_rotations(samples.time, rotation, ROTATION_FILTER)
    psi, missing = hack_weights(weights)
    return ExpressionTrack(psi, samples.time.copy(), video.fps, None, missing, str(video.path),
                           rotation.astype(np.float32), samples.found.copy())


FACE_FRAMES_FILE = "face_frames.csv"


def write_face_frames(path: str | Path, track: ExpressionTrack) -> None:
    """One row per video frame: ``frame, time`` (s), ``face`` (1 found, 0 filled in by interpolation)."""
    write_csv(path, {"frame": np.arange(len(track)), "time": track.time, "face": track.tracked.astype(np.int8)},
              float_format="%.6f")
