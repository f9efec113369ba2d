"""Colour frames of a video file, with the video's own timestamps, for the face stage.

``open_video(path)`` checks that OpenCV reads the file as a video (``cv2.VideoCapture`` opens it and its
first frame decodes) and gives a :class:`VideoFrames`: ``fps`` and ``count`` from the container's header,
and ``frames()`` yielding ``(index, seconds, rgb uint8 [H,W,3])``.

Timestamps: ``CAP_PROP_POS_MSEC`` of each frame (its presentation time; variable-rate phone videos keep
their timing), taken as ``index / fps`` when the container gives none or they do not increase.  The first
frame is at 0 s.

A frame that does not decode before the header's frame count is reached (a truncated or corrupt file)
is an InputError naming the frame; a header that overstates the count by a frame or two (some encoders
do) is within :data:`COUNT_SLACK`.
"""
from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from base.errors import InputError, require_file

COUNT_SLACK = 0  # frames the header may overstate before the missing ones count as corrupt
# The file suffixes read as videos (through OpenCV's FFmpeg): a take's face video here, a normal-map video in
# the tracker (``motion.track.sources``).
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv")


@contextlib.contextmanager
def quiet_stderr():
    """Standard error (file descriptor 2) sent to /dev/null for the block: FFmpeg (under OpenCV) and
    MediaPipe's C++ graph log lines of their own there (a broken atom, XNNPACK), which would bury the
    one-line error of ``base.cli``; the errors they meet reach the user as InputError instead."""
    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


@dataclass
class VideoFrames:
    """A video file opened for the face stage (see the module docstring)."""

    path: Path
    fps: float
    count: int
    width: int
    height: int

    def frames(self) -> Iterator[tuple[int, float, np.ndarray]]:
        """(index, seconds from the first frame, RGB uint8 [H,W,3]) for every frame."""
        with quiet_stderr():
            capture = cv2.VideoCapture(str(self.path))
        previous, index = -1.0, 0
        try:
            while True:
                with quiet_stderr():
                    ok, image = capture.read()
                if not ok:
                    break
                stamp = capture.get(cv2.CAP_PROP_POS_MSEC) / 1000.0
                seconds = stamp if (index == 0 or stamp > previous) and np.isfinite(stamp) else index / self.fps
                if index > 0 and seconds <= previous:
                    seconds = previous + 1.0 / self.fps
                if index == 0:
                    origin = seconds
                previous = seconds
                if image.ndim != 3 or image.shape[2] != 3 or image.shape[:2] != (self.height, self.width):
                    raise InputError(f"{self.path}: frame {index} of shape {image.shape}, expected colour frames "
                                     f"{self.height}x{self.width}x3 as the header says")
                yield index, seconds - origin, cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
                index += 1
        finally:
            capture.release()
        if index < self.count - COUNT_SLACK:
            raise InputError(f"{self.path}: frame {index} of {self.count} does not decode (a truncated or corrupt "
                             f"video); expected {self.count} frames as its header says")


def open_video(path: str | Path) -> VideoFrames:
    """The video at ``path``, checked to be one OpenCV decodes (InputError naming the file otherwise)."""
    path = require_file(path, "video")
    with quiet_stderr():
        capture = cv2.VideoCapture(str(path))
    try:
        if not capture.isOpened():
            raise InputError(f"{path}: not a video OpenCV can open; expected a video file (.mp4, .mov, .avi, ...)")
        with quiet_stderr():
            ok, image = capture.read()
        if not ok or image is None:
            raise InputError(f"{path}: no frame decodes; expected a video file (.mp4, .mov, .avi, ...)")
        fps = float(capture.get(cv2.CAP_PROP_FPS))
        count = int(capture.get(cv2.CAP_PROP_FRAME_COUNT))
    finally:
        capture.release()
    if not np.isfinite(fps) or fps <= 0:
        raise InputError(f"{path}: the video gives no frame rate ({fps}); expected a video with timestamps")
    return VideoFrames(path, fps, max(count, 1), image.shape[1], image.shape[0])
