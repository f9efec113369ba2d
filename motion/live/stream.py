"""One phone's stream (device id + subject): its frames on the capture's clock, resampled causally to the
output rate, each output frame run through the larynx model's step and head2neck as it completes
(:func:`run_pending`, once per drain of the socket, all phones' frames in one head2neck batch).

Equal to ``infer.py`` on the recorded ``capture.csv`` by construction: the frame times are those
``base.timebase.parse_timecode`` reads back from the CSV's timecode (``HH:MM:SS:FF.fff`` at the stream's
integer rate), the output grid is ``resample_uniform``'s (``k / fps`` from the first frame, while not past
the last frame, within 1e-4 frame), each grid point is ``np.interp``'s linear interpolation between the two
frames around it (float64, cast to float32 for psi as ``ExpressionTrack.resampled`` does), and a frame
number gap is interpolated over exactly as the reader interpolates over rows it does not have.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from data.expressions import WEIGHT_RANGE
from models.head2neck import predict_theta
from motion.head2neck import UNITS, head_rotations_from_ypr
from motion.live.packet import NUM_WEIGHTS, Frame, PacketError
from motion.pipeline.models import Models


@dataclass
class StreamOptions:
    """What every phone's stream shares: the head conventions, eta and the limits on what is accepted."""

    head_units: str = "rad"
    signs: tuple[float, float, float] = (1.0, 1.0, 1.0)
    recenter: bool = False
    eta: float = 1.0
    max_gap_seconds: float = 10.0


@dataclass
class Recorded:
    """What a stream keeps for its files: the accepted frames (for capture.csv) and the output frames."""

    frames: list[int] = field(default_factory=list)
    subframes: list[float] = field(default_factory=list)
    values: list[np.ndarray] = field(default_factory=list)  # [61] float32 as accepted (weights clamped)
    psi: list[np.ndarray] = field(default_factory=list)     # per output frame [55] float32
    tau: list[float] = field(default_factory=list)
    theta: list[np.ndarray] = field(default_factory=list)   # per output frame [J,3] float32
    latency_ms: list[float] = field(default_factory=list)   # receipt of the completing datagram -> its params


def frame_seconds(frame: int, subframe: float, rate: int) -> float:
    """Seconds of a timecode frame as ``parse_timecode`` computes them from ``HH:MM:SS:FF.fff`` (the
    sub-frame kept to the 3 decimals the CSV holds)."""
    seconds, ff = divmod(int(frame), rate)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return hours * 3600 + minutes * 60 + secs + (ff + round(float(subframe), 3)) / rate


def timecode(frame: int, subframe: float, rate: int) -> str:
    """``HH:MM:SS:FF.fff`` of a frame number at an integer rate (Live Link Face's CSV timecode)."""
    seconds, ff = divmod(int(frame), rate)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours:02d}:{minutes:02d}:{secs:02d}:{ff + round(float(subframe), 3):06.3f}"


class PhoneStream:
    """The state of one phone: accept its frames in order (:meth:`accept`), keep what its files need."""

    def __init__(self, device: str, subject: str, rate: tuple[int, int], models: Models, options: StreamOptions):
        self.device, self.subject, self.rate = device, subject, rate
        self.timecode_rate = int(round(rate[0] / rate[1]))
        self.models, self.options = models, options
        larynx = models.larynx
        self.fps = float(larynx.fps) if larynx is not None else rate[0] / rate[1]
        self.larynx = None
        if larynx is not None:
            larynx.eval()
            self.larynx = larynx.stream(1, torch.tensor([0]))  # 0: the average style, as predict_tau's None
        self.scale = UNITS[options.head_units] * np.asarray(options.signs, dtype=np.float64)
        self.origin: float | None = None     # seconds of the first frame (the grid's 0)
        self.previous: tuple[float, np.ndarray, np.ndarray] | None = None  # (t, psi [55] f32, head [3] f64)
        self.last_frame = -1
        self.next_index = 0                  # the next output grid point k (time k / fps)
        self.first_head: torch.Tensor | None = None
        self.missing = self.late = self.clamped = 0
        self.recorded = Recorded()
        self.pending: list[tuple[np.ndarray, np.ndarray, int]] = []  # output frames not yet run (psi, ypr, ns)

    @property
    def key(self) -> tuple[str, str]:
        return self.device, self.subject

    def check(self, frame: Frame) -> None:
        """PacketError (nothing changed) when ``frame`` cannot continue this stream."""
        if frame.rate != self.rate:
            raise PacketError("rate", 0, f"rate {frame.rate[0]}/{frame.rate[1]}, expected the stream's "
                                         f"{self.rate[0]}/{self.rate[1]}")
        if frame.frame <= self.last_frame:
            self.late += 1
            raise PacketError("late", 0, f"frame {frame.frame} after frame {self.last_frame}")
        if self.last_frame >= 0 and frame.frame - self.last_frame > self.options.max_gap_seconds * self.fps_in:
            raise PacketError("jump", 0, f"frame {frame.frame} after {self.last_frame}: a gap over "
                                         f"max_gap_seconds={self.options.max_gap_seconds:g}")
        radians = np.abs(frame.head_ypr.astype(np.float64) * self.scale)
        if radians.max() > np.pi + 1e-6:  # head_rotations_from_ypr's own bound: wrong units or garbage
            raise PacketError("absurd", 0, f"head angles up to {radians.max():.3g} rad after "
                                           f"head_units={self.options.head_units}; expected at most pi")

    @property
    def fps_in(self) -> float:
        return self.rate[0] / self.rate[1]

    def accept(self, frame: Frame, received_ns: int) -> int:
        """Take the next frame (PacketError if it cannot be: see :meth:`check`); queue every output frame it
        completes (:func:`run_pending` runs them).  Returns the number of output frames queued."""
        self.check(frame)
        values = frame.values.copy()
        lo, hi = WEIGHT_RANGE  # the reader refuses weights outside it: clamp so capture.csv reads back
        outside = (values[:NUM_WEIGHTS] < lo) | (values[:NUM_WEIGHTS] > hi)
        if outside.any():
            self.clamped += int(outside.sum())
            values[:NUM_WEIGHTS] = np.clip(values[:NUM_WEIGHTS], lo, hi)
        if self.last_frame >= 0:
            self.missing += frame.frame - self.last_frame - 1
        self.last_frame = frame.frame
        record = self.recorded
        record.frames.append(frame.frame)
        record.subframes.append(round(float(frame.subframe), 3))
        record.values.append(values)
        accepted = Frame(frame.device, frame.subject, frame.frame, frame.subframe, frame.rate, values)
        seconds = frame_seconds(frame.frame, frame.subframe, self.timecode_rate)
        if self.origin is None:
            self.origin = seconds
        t = seconds - self.origin
        current = (t, accepted.psi(), values[NUM_WEIGHTS:NUM_WEIGHTS + 3].astype(np.float64))
        produced = 0
        previous = self.previous if self.previous is not None else current
        # resample_uniform's grid: k / fps while k <= t * fps + 1e-4 (stamps within 1e-4 frame)
        while self.next_index <= np.floor(t * self.fps + 1e-4):
            grid = self.next_index / self.fps
            span = current[0] - previous[0]
            w = 0.0 if span <= 0 else min(max((grid - previous[0]) / span, 0.0), 1.0)
            psi = (previous[1].astype(np.float64) + w * (current[1].astype(np.float64)
                                                         - previous[1].astype(np.float64))).astype(np.float32)
            head = previous[2] + w * (current[2] - previous[2])
            self.emit(psi, head, received_ns)
            self.next_index += 1
            produced += 1
        self.previous = current
        return produced

    def emit(self, psi: np.ndarray, head_ypr: np.ndarray, received_ns: int) -> None:
        """Queue one output frame for :func:`run_pending` (which runs the models on it)."""
        self.pending.append((psi, head_ypr, received_ns))

    def latency(self) -> dict:
        """Receipt -> params latency of the output frames, ms: p50, p99, max (None without frames)."""
        values = np.asarray(self.recorded.latency_ms)
        if not len(values):
            return {"p50": None, "p99": None, "max": None}
        return {"p50": round(float(np.percentile(values, 50)), 3), "p99": round(float(np.percentile(values, 99)), 3),
                "max": round(float(values.max()), 3)}


def run_pending(streams: list[PhoneStream], models: Models, options: StreamOptions) -> int:
    """Run the queued output frames of every stream: the larynx step per stream in frame order (tau), and
    head2neck on all of them in one batch (theta; one frame costs about what four do: the per-call
    overhead dominates), as infer.py's ``head_theta`` does (units, signs, recentring on the stream's first
    frame).  Each frame's latency is from its datagram's receipt to the end of this call.  Returns the
    number of frames run."""
    owners = [(stream, item) for stream in streams for item in stream.pending]
    if not owners:
        return 0
    with torch.inference_mode():
        taus = []
        for stream, (psi, _, _) in owners:
            taus.append(0.0 if stream.larynx is None else float(stream.larynx.step(torch.from_numpy(psi)[None]).item()))
        theta = np.zeros((len(owners), models.rig.num_joints, 3), dtype=np.float32)
        if models.neck is not None:
            ypr = np.stack([item[1] for _, item in owners])
            head = head_rotations_from_ypr(ypr, options.head_units, options.signs, "HeadYaw, HeadPitch, HeadRoll")
            if options.recenter:
                for k, (stream, _) in enumerate(owners):
                    if stream.first_head is None:
                        stream.first_head = head[k].clone()
                    head[k] = stream.first_head.T @ head[k]
            theta = predict_theta(models.neck, models.rig, head).numpy()
    done = time.perf_counter_ns()
    for k, (stream, (psi, _, received_ns)) in enumerate(owners):
        record = stream.recorded
        record.psi.append(psi)
        record.tau.append(taus[k])
        record.theta.append(theta[k])
        record.latency_ms.append((done - received_ns) / 1e6)
    for stream in streams:
        stream.pending.clear()
    return len(owners)
