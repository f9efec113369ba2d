"""One phone's stream (device id + subject): its frames on the capture's clock, resampled causally to the
output rate, each output frame run through the larynx model's step and head2neck as it completes
(:func:`run_pending`, once per drain of the socket, all phones' frames in one head2neck batch).

Equal to ``infer.py`` on the recorded ``capture.csv`` by construction: the frame times are those
``base.timebase.parse_timecode`` reads back from the CSV's timecode (``HH:MM:SS:FF.fff`` at the stream's
integer rate), the output grid is ``resample_uniform``'s (``k / fps`` from the first frame, within
``GRID_TOLERANCE``), each grid point is ``np.interp``'s linear interpolation between the two frames around it
(float64, cast to float32 for psi as ``ExpressionTrack.resampled`` does), and gaps follow the one gap rule
(``base.timebase.GAP_SECONDS``, docs/conventions.md "Gaps"): frames no more than 0.25 s apart are interpolated
over, the grid points inside a longer gap repeat the last output frame (psi, tau, theta: no model runs) and
the larynx model restarts from its initial state at the frame after it, as ``motion.pipeline.animate`` does.

What a datagram may cost is bounded before anything changes (:meth:`PhoneStream.check`): a frame-number jump
of at most ``max_gap_seconds``, a capture clock at most ``max_lead_seconds`` ahead of the receiver's since
the stream's first frame (so a stream records no faster than real time, whatever it sends), and so at most
``max_frames_per_datagram`` output frames, of which at most ``GAP_SECONDS * fps + 1`` run the models.
"""
from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from base.timebase import GAP_SECONDS, first_grid_index, last_grid_index
from data.expressions import WEIGHT_RANGE
from models.head2neck import predict_theta
from motion.head2neck import UNITS, head_rotations_from_ypr
from motion.live.packet import NUM_WEIGHTS, VALUE_COUNT, Frame, PacketError
from motion.pipeline.models import Models

SUBFRAME_DIGITS = 3  # the CSV's timecode keeps the sub-frame to 3 decimals (Live Link Face's own)


@dataclass
class StreamOptions:
    """What every phone's stream shares: the head conventions, eta and the limits on what is accepted."""

    head_units: str = "rad"
    signs: tuple[float, float, float] = (1.0, 1.0, 1.0)
    recenter: bool = False
    eta: float = 1.0
    max_gap_seconds: float = 10.0   # a frame-number jump beyond this is refused ("jump")
    max_lead_seconds: float = 30.0  # capture clock ahead of the receiver's by more: refused ("ahead")


@dataclass
class Recorded:
    """What a stream keeps for its files: counts of the accepted frames (their rows go to capture.csv as they
    come: :attr:`PhoneStream.rows`) and the output frames.  A held frame refers to the arrays of the frame
    it repeats (a gap costs a reference per frame, not a copy)."""

    frames: int = 0                                         # accepted datagrams
    psi: list[np.ndarray] = field(default_factory=list)     # per output frame [55] float32
    tau: list[float] = field(default_factory=list)
    theta: list[np.ndarray] = field(default_factory=list)   # per output frame [J,3] float32
    latency_ms: list[float] = field(default_factory=list)   # receipt of the completing datagram -> its params
    held: int = 0                                           # output frames inside gaps (the gap rule)


def frame_seconds(frame: int, subframe: float, rate: int) -> float:
    """Seconds of a timecode frame as ``parse_timecode`` computes them from ``HH:MM:SS:FF.fff`` (the
    sub-frame kept to the 3 decimals the CSV holds)."""
    seconds, ff = divmod(int(frame), rate)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return hours * 3600 + minutes * 60 + secs + (ff + kept_subframe(subframe)) / rate


def kept_subframe(subframe: float) -> float:
    """The sub-frame as the CSV keeps it: 3 decimals, below 1 (0.9996 would print as the next frame)."""
    return min(round(float(subframe), SUBFRAME_DIGITS), 0.999)


def timecode(frame: int, subframe: float, rate: int) -> str:
    """``HH:MM:SS:FF.fff`` of a frame number at an integer rate (Live Link Face's CSV timecode)."""
    seconds, ff = divmod(int(frame), rate)
    hours, rest = divmod(seconds, 3600)
    minutes, secs = divmod(rest, 60)
    return f"{hours:02d}:{minutes:02d}:{secs:02d}:{ff + kept_subframe(subframe):06.3f}"


def capture_row(frame: int, subframe: float, rate: int, values: np.ndarray) -> str:
    """One line of capture.csv (``Timecode,BlendShapeCount,<61 values>``); 9 significant digits: a float32
    reads back exactly."""
    return (f"{timecode(frame, subframe, rate)},{VALUE_COUNT}," + ",".join(f"{float(v):.9g}" for v in values)
            + "\n")


class PhoneStream:
    """The state of one phone: accept its frames in order (:meth:`accept`), keep what its files need."""

    def __init__(self, device: str, subject: str, rate: tuple[int, int], models: Models, options: StreamOptions,
                 address: tuple[str, int] | None = None):
        self.device, self.subject, self.rate, self.address = device, subject, rate, address
        self.timecode_rate = int(round(rate[0] / rate[1]))
        self.models, self.options = models, options
        larynx = models.larynx
        self.fps = float(larynx.fps) if larynx is not None else rate[0] / rate[1]
        self.larynx = self.spare = None
        if larynx is not None:
            larynx.eval()
            self.larynx = self.fresh_larynx()
        self.scale = UNITS[options.head_units] * np.asarray(options.signs, dtype=np.float64)
        self.max_frames_per_datagram = int(np.ceil(options.max_gap_seconds * self.fps)) + 2
        self.origin: float | None = None     # seconds of the first frame (the grid's 0)
        self.first_ns: int | None = None     # receipt of the first frame (perf_counter_ns)
        self.last_ns: int | None = None      # receipt of the last accepted frame
        self.previous: tuple[float, np.ndarray, np.ndarray] | None = None  # (t, psi [55] f32, head [3] f64)
        self.last_frame = -1
        self.next_index = 0                  # the next output grid point k (time k / fps)
        self.first_head: torch.Tensor | None = None
        self.missing = self.late = self.clamped = self.gaps = 0
        self.recorded = Recorded()
        self.rows: list[str] = []            # capture.csv lines not yet written (motion.live.outputs)
        self.folder: str | None = None       # its folder in the session (motion.live.outputs)
        self.closed: str | None = None       # why it was closed: "stop", "idle", "error: ..."
        # output frames not yet run, in order: ("frame", psi, ypr, received_ns), ("held", count), ("restart",)
        self.pending: list[tuple] = []

    def fresh_larynx(self):
        return self.models.larynx.stream(1, torch.tensor([0]))  # 0: the average style, as predict_tau's None

    def prepare(self) -> bool:
        """Make the larynx stream a gap restarts from ahead (about two steps' cost), while the socket is idle,
        not when the frame after a gap arrives; whether one was made."""
        if self.larynx is None or self.spare is not None:
            return False
        self.spare = self.fresh_larynx()
        return True

    def restart(self) -> None:
        """The gap rule's restart: the larynx model from its initial state (the one made ahead, if any)."""
        if self.larynx is not None:
            self.larynx, self.spare = (self.spare if self.spare is not None else self.fresh_larynx()), None

    @property
    def key(self) -> tuple[str, str]:
        return self.device, self.subject

    @property
    def fps_in(self) -> float:
        return self.rate[0] / self.rate[1]

    def seconds(self, frame: Frame) -> float:
        """The frame's time on the stream's clock (0 at its first frame)."""
        seconds = frame_seconds(frame.frame, frame.subframe, self.timecode_rate)
        return seconds - (seconds if self.origin is None else self.origin)

    def check(self, frame: Frame, received_ns: int | None = None) -> None:
        """PacketError (nothing changed) when ``frame`` cannot continue this stream, or would cost more than
        the limits allow."""
        if frame.rate != self.rate:
            raise PacketError("rate", 0, f"rate {frame.rate[0]}/{frame.rate[1]}, expected the stream's "
                                         f"{self.rate[0]}/{self.rate[1]}")
        if frame.frame <= self.last_frame:
            self.late += 1
            raise PacketError("late", 0, f"frame {frame.frame} after frame {self.last_frame}")
        if self.last_frame >= 0 and frame.frame - self.last_frame > self.options.max_gap_seconds * self.fps_in:
            raise PacketError("jump", 0, f"frame {frame.frame} after {self.last_frame}: a gap over "
                                         f"max_gap_seconds={self.options.max_gap_seconds:g}")
        t = self.seconds(frame)
        if received_ns is not None and self.first_ns is not None:
            wall = (received_ns - self.first_ns) / 1e9
            if t > wall + self.options.max_lead_seconds:
                raise PacketError("ahead", 0, f"frame {frame.frame}: {t:.3f} s into the stream after {wall:.3f} s "
                                              f"of it; expected at most max_lead_seconds="
                                              f"{self.options.max_lead_seconds:g} ahead")
        completed = last_grid_index(t, self.fps) - self.next_index + 1
        if completed > self.max_frames_per_datagram:
            raise PacketError("jump", 0, f"frame {frame.frame} completes {completed} output frames, expected at "
                                         f"most {self.max_frames_per_datagram}")
        radians = np.abs(frame.head_ypr.astype(np.float64) * self.scale)
        if radians.max() > np.pi + 1e-6:  # head_rotations_from_ypr's own bound: wrong units or garbage
            raise PacketError("absurd", 0, f"head angles up to {radians.max():.3g} rad after "
                                           f"head_units={self.options.head_units}; expected at most pi")

    def accept(self, frame: Frame, received_ns: int) -> int:
        """Take the next frame (PacketError if it cannot be: see :meth:`check`); queue every output frame it
        completes (:func:`run_pending` runs them).  Returns the number of output frames queued."""
        self.check(frame, received_ns)
        values = frame.values.copy()
        lo, hi = WEIGHT_RANGE  # the reader refuses weights outside it: clamp so capture.csv reads back
        outside = (values[:NUM_WEIGHTS] < lo) | (values[:NUM_WEIGHTS] > hi)
        if outside.any():
            self.clamped += int(outside.sum())
            values[:NUM_WEIGHTS] = np.clip(values[:NUM_WEIGHTS], lo, hi)
        if self.origin is None:
            self.origin = frame_seconds(frame.frame, frame.subframe, self.timecode_rate)
            self.first_ns = received_ns
        t = self.seconds(frame)
        if self.last_frame >= 0:
            self.missing += frame.frame - self.last_frame - 1
        self.last_frame, self.last_ns = frame.frame, received_ns
        self.recorded.frames += 1
        self.rows.append(capture_row(frame.frame, frame.subframe, self.timecode_rate, values))
        accepted = Frame(frame.device, frame.subject, frame.frame, frame.subframe, frame.rate, values)
        current = (t, accepted.psi(), values[NUM_WEIGHTS:NUM_WEIGHTS + 3].astype(np.float64))
        produced = 0
        if self.previous is not None and t - self.previous[0] > GAP_SECONDS:
            # the gap rule: the points before this frame repeat the last output frame; the larynx restarts
            resume = first_grid_index(t, self.fps)
            if resume > self.next_index:
                self.pending.append(("held", resume - self.next_index))
                produced += resume - self.next_index
                self.next_index = resume
            self.pending.append(("restart",))
            self.previous = None
            self.gaps += 1
        previous = self.previous if self.previous is not None else current
        last = last_grid_index(t, self.fps)
        while self.next_index <= last:
            grid = self.next_index / self.fps
            span = current[0] - previous[0]
            w = 0.0 if span <= 0 else min(max((grid - previous[0]) / span, 0.0), 1.0)
            psi = (previous[1].astype(np.float64) + w * (current[1].astype(np.float64)
                                                         - previous[1].astype(np.float64))).astype(np.float32)
            head = previous[2] + w * (current[2] - previous[2])
            self.pending.append(("frame", psi, head, received_ns))
            self.next_index += 1
            produced += 1
        self.previous = current
        return produced

    def latency(self) -> dict:
        """Receipt -> params latency of the output frames run, ms: p50, p99, max (None without frames)."""
        values = np.asarray(self.recorded.latency_ms)
        if not len(values):
            return {"p50": None, "p99": None, "max": None}
        return {"p50": round(float(np.percentile(values, 50)), 3), "p99": round(float(np.percentile(values, 99)), 3),
                "max": round(float(values.max()), 3)}


def _taus(stream: PhoneStream) -> list[float]:
    """The larynx step over the stream's pending frames, in order (restarting where the gap rule says)."""
    taus = []
    for item in stream.pending:
        if item[0] == "restart":
            stream.restart()
        elif item[0] == "frame":
            taus.append(0.0 if stream.larynx is None
                        else float(stream.larynx.step(torch.from_numpy(item[1])[None]).item()))
    return taus


def _thetas(streams: list[PhoneStream], models: Models, options: StreamOptions) -> np.ndarray:
    """head2neck on the pending frames of ``streams`` in one batch [N,J,3] (units, signs, recentring on the
    stream's first frame, as infer.py's ``head_theta``)."""
    items = [(stream, item) for stream in streams for item in stream.pending if item[0] == "frame"]
    theta = np.zeros((len(items), models.rig.num_joints, 3), dtype=np.float32)
    if models.neck is None or not items:
        return theta
    ypr = np.stack([item[2] for _, item in items])
    head = head_rotations_from_ypr(ypr, options.head_units, options.signs, "HeadYaw, HeadPitch, HeadRoll")
    if options.recenter:
        for k, (stream, _) in enumerate(items):
            if stream.first_head is None:
                stream.first_head = head[k].clone()
            head[k] = stream.first_head.T @ head[k]
    return predict_theta(models.neck, models.rig, head).numpy()


def run_pending(streams: list[PhoneStream], models: Models, options: StreamOptions,
                failed: dict | None = None) -> list[tuple[PhoneStream, int]]:
    """Run the queued output frames of every stream: the larynx step per stream in frame order (tau), and
    head2neck on all of them in one batch (theta; one frame costs about what four do: the per-call
    overhead dominates).  Held frames (the gap rule) repeat the stream's last output frame without running
    anything.  Each frame's latency is from its datagram's receipt to the end of this call.

    A stream whose frames raise is left out (its pending frames dropped) and named in ``failed``
    (stream key -> the error), the others go on.  Returns (stream, output index) of the frames run."""
    failed = {} if failed is None else failed
    ready: list[PhoneStream] = []
    taus: dict[int, list[float]] = {}
    with torch.inference_mode():
        for stream in streams:
            if not stream.pending:
                continue
            try:
                taus[id(stream)] = _taus(stream)
                ready.append(stream)
            except Exception as e:  # noqa: BLE001 -- one stream's failure must not touch the others
                failed[stream.key] = f"{type(e).__name__}: {e}"
                stream.pending.clear()
        try:
            theta = _thetas(ready, models, options)
            thetas = {}
            start = 0
            for stream in ready:
                count = sum(1 for item in stream.pending if item[0] == "frame")
                thetas[id(stream)] = theta[start:start + count]
                start += count
        except Exception:  # noqa: BLE001 -- find the stream that fails, run the others on their own
            thetas = {}
            for stream in list(ready):
                try:
                    thetas[id(stream)] = _thetas([stream], models, options)
                except Exception as e:  # noqa: BLE001
                    failed[stream.key] = f"{type(e).__name__}: {e}"
                    stream.pending.clear()
                    ready.remove(stream)
    done = time.perf_counter_ns()
    ran = []
    for stream in ready:
        record, stream_taus, stream_theta = stream.recorded, taus[id(stream)], thetas[id(stream)]
        k = 0
        for item in stream.pending:
            if item[0] == "frame":
                record.psi.append(item[1])
                record.tau.append(stream_taus[k])
                record.theta.append(stream_theta[k])
                record.latency_ms.append((done - item[3]) / 1e6)
                ran.append((stream, len(record.tau) - 1))
                k += 1
            elif item[0] == "held":
                count = item[1]
                record.psi.extend([record.psi[-1]] * count)
                record.tau.extend([record.tau[-1]] * count)
                record.theta.extend([record.theta[-1]] * count)
                record.held += count
        stream.pending.clear()
    return ran
