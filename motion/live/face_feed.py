"""The live mode on a webcam or a video file: ``python -m motion.live camera=0`` / ``video=clip.mp4``.

Each frame goes through the face stage's landmarker (``motion.face``: the same model, VIDEO mode, the
same name mapping and axis conversion as ``infer.py expressions=clip.mp4``) and becomes what a phone
sends: a ``motion.live.packet.Frame`` of 52 ARKit weights (Unreal's order) and HeadYaw, HeadPitch, HeadRoll
in radians (``base.rotations.matrix_to_ypr_np`` of the rotation, the rig's convention: the stream runs with
``head_units=rad`` and +1 signs).  One :class:`motion.live.stream.PhoneStream` (device ``camera<N>`` or the
video's name, subject ``face``) resamples, runs the larynx step and head2neck, feeds the live view, and the
session is written as the UDP mode writes it (``<subject>/params.npz``, ``capture.csv``, ``summary.json``).

Frame numbers count the source's frames at its integer rate (a 29.97 fps source runs as 30): a video is
paced at that rate (``realtime=false`` runs it as fast as it decodes); a camera at whatever it delivers,
numbered by its arrival time.  Frames without a face are counted (``rejected.no_face``) and skipped; the
stream interpolates over them as over lost datagrams.  ``mirror=true``: selfie-mirrored frames (left and
right weights swapped, yaw and roll negated, ``ExpressionTrack.mirrored``'s convention).
"""
from __future__ import annotations

import time
from collections import Counter
from pathlib import Path

import cv2
import numpy as np

from base.errors import InputError
from base.files import atomic_folder
from base.rotations import matrix_to_ypr_np, nearest_rotation_np
from motion.face.frames import open_video, quiet_stderr
from motion.face.model import find_face_model, open_landmarker, require_mediapipe
from motion.face.tracking import ARKIT_INDEX, detect
from motion.live.outputs import write_session
from motion.live.packet import EAR_BLENDSHAPES, NUM_WEIGHTS, VALUE_COUNT, Frame, PacketError
from motion.live.stream import PhoneStream, StreamOptions, run_pending
from motion.pipeline.models import Models

SUBJECT = "face"
_MIRROR_NAME = {"left": "right", "right": "left"}


def _ear_index(mirror: bool) -> np.ndarray:
    """For each of Unreal's 52 names, the column of ``motion.face.ARKIT_NAMES`` that feeds it (-1: none, TongueOut)."""
    out = []
    for name in EAR_BLENDSHAPES:
        lower = name.lower()
        if mirror:
            for side, other in _MIRROR_NAME.items():
                if lower.endswith(side):
                    lower = lower[: -len(side)] + other
                    break
        out.append(ARKIT_INDEX.get(lower, -1))
    return np.asarray(out)


def frame_values(weights: np.ndarray, matrix: np.ndarray, ear_index: np.ndarray, mirror: bool) -> np.ndarray:
    """The 61 values of a Live Link Face frame [61] float32 from the landmarker's weights [52] and matrix [4,4]."""
    values = np.zeros(VALUE_COUNT, dtype=np.float32)
    driven = ear_index >= 0
    values[:NUM_WEIGHTS][driven] = weights[ear_index[driven]]
    ypr = matrix_to_ypr_np(nearest_rotation_np(np.asarray(matrix, dtype=np.float64)[:3, :3]))
    if mirror:
        ypr = ypr * np.array([-1.0, 1.0, -1.0])
    values[NUM_WEIGHTS:NUM_WEIGHTS + 3] = ypr
    return values


class FaceFeed:
    """A camera (``camera`` index) or a video file (``video``) driving one live stream."""

    def __init__(self, models: Models, camera: int | None = None, video: str | None = None,
                 face_model: str | None = None, mirror: bool = False, realtime: bool = True, eta: float = 1.0,
                 recenter: bool = False, announce=print, on_frame=None):
        if (camera is None) == (video is None):
            raise InputError("give camera=<index> or video=<file>, not both")
        require_mediapipe()
        self.model_path = find_face_model(face_model)
        self.models, self.mirror, self.realtime = models, mirror, realtime
        self.announce, self.on_frame = announce, on_frame
        if video is not None:
            source = open_video(video)       # InputError naming the file when it is not a video
            self.capture_path, fps = str(source.path), source.fps
            self.device = source.path.stem
        else:
            with quiet_stderr():
                capture = cv2.VideoCapture(int(camera))
            ok = capture.isOpened() and capture.read()[0]
            fps = float(capture.get(cv2.CAP_PROP_FPS)) or 30.0
            capture.release()
            if not ok:
                raise InputError(f"camera={camera}: no camera there gives frames (is it connected, or busy?)")
            self.capture_path, self.device = int(camera), f"camera{camera}"
        self.rate = (max(1, int(round(fps))), 1)
        # a video decodes faster than real time (realtime=false): no bound on its clock's lead
        self.options = StreamOptions("rad", (1.0, 1.0, 1.0), recenter, eta, max_gap_seconds=10.0,
                                     max_lead_seconds=float("inf"))
        self.stream = PhoneStream(self.device, SUBJECT, self.rate, models, self.options)
        self.rejected: Counter = Counter()
        self.received = self.produced = 0
        self.ear_index = _ear_index(mirror)

    @property
    def streams(self) -> list[PhoneStream]:
        return [self.stream] if self.stream.recorded.frames else []

    def run(self, duration: float | None, should_stop, status_seconds: float = 5.0) -> None:
        """Read, track and stream frames until the source ends, ``should_stop()`` or ``duration`` seconds."""
        landmarker = open_landmarker(self.model_path)
        with quiet_stderr():
            capture = cv2.VideoCapture(self.capture_path)
        fps = self.rate[0] / self.rate[1]
        start = last_status = time.monotonic()
        index, last_frame = 0, -1
        try:
            while not should_stop():
                now = time.monotonic()
                if duration is not None and now - start >= duration:
                    break
                with quiet_stderr():
                    ok, image = capture.read()
                if not ok:
                    break
                received_ns = time.perf_counter_ns()
                self.received += 1
                if isinstance(self.capture_path, int):   # a camera: numbered by arrival
                    number = max(int(round((time.monotonic() - start) * fps)), last_frame + 1)
                else:
                    number = index
                    if self.realtime:                   # a video: at its own rate
                        time.sleep(max(0.0, start + number / fps - time.monotonic()))
                index += 1
                face = detect(landmarker, cv2.cvtColor(image, cv2.COLOR_BGR2RGB), int(round(1000 * number / fps)))
                if face is None:
                    self.rejected["no_face"] += 1
                    continue
                frame = Frame(self.device, SUBJECT, number, 0.0, self.rate,
                              frame_values(face[0], face[1], self.ear_index, self.mirror))
                last_frame = number
                try:
                    self.produced += self.stream.accept(frame, received_ns)
                except PacketError as e:  # e.g. a jump past max_gap_seconds: counted, the feed goes on
                    self.rejected[e.reason] += 1
                    continue
                before = len(self.stream.recorded.tau)
                run_pending([self.stream], self.models, self.options)
                if self.on_frame is not None:
                    try:
                        for k in range(before, len(self.stream.recorded.tau)):
                            self.on_frame(self.stream, k)
                    except Exception:  # noqa: BLE001 -- the live view must never stop the feed
                        pass
                if status_seconds and now - last_status >= status_seconds:
                    self.announce(f"live: {self.device}: {self.received} frames read, {self.produced} out, "
                                  f"no face in {self.rejected['no_face']}")
                    last_status = now
        finally:
            capture.release()
            landmarker.close()
        if self.received and not self.stream.recorded.frames:
            raise InputError(f"{self.device}: no face found in any of its {self.received} frames; expected a "
                             f"face in view")


def write_feed(feed: FaceFeed, out_dir: Path, eta: float) -> dict:
    """The session into ``out_dir``, whole or not at all (the UDP mode's files); the summary."""
    with atomic_folder(out_dir) as staging:
        return write_session(staging, feed.streams, dict(feed.rejected), eta,
                             {"source": str(feed.capture_path), "frames_read": feed.received})
