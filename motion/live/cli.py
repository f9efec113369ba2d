"""Drive the neck and larynx from the Live Link Face stream: ``python -m motion.live``.

    python -m motion.live [host=0.0.0.0] [port=11111] [out_dir=DIR] [duration=SECONDS] [allow=[IP,NET/24]] \\
        [checkpoint=default|none|path] [head2neck=default|none|path] [rig=hack_rig.npz] \\
        [viewer=true] [viewer_port=8765] [viewer_host=127.0.0.1]
    python -m motion.live.send take=take.csv [host=127.0.0.1] [port=11111] [speed=1.0]   # no phone at hand
    python -m motion.live camera=0 [mirror=true] [viewer=true]     # a webcam through the face stage (".[video]")
    python -m motion.live video=clip.mp4 [realtime=false]          # a face video at its own rate

Receives Live Link Face "ARKit" mode datagrams (packet version 6, ``motion.live.packet``) on UDP ``port``;
in the app: Settings -> Live Link -> add a target with this machine's IP address and port 11111.  Every
phone (device id + subject) gets its own stream: its frames are resampled causally to the larynx model's
rate (the shipped model: 30 fps; without one, the stream's) as ``infer.py`` resamples, and each output
frame runs the larynx model's step (tau) and head2neck (theta) as it completes.  Late or out-of-order
frames are dropped, gaps follow the gap rule (``base.timebase.GAP_SECONDS``: under 0.25 s interpolated
over, longer ones held at no cost), weights outside ``data.expressions.WEIGHT_RANGE`` clamped and counted;
datagrams too short, of another version (MetaHuman Animator mode, old apps), with a field out of range
(rate 1..240 fps, sub-frame in [0,1), frame of the day), a wrong count, bad names, NaN/Inf or absurd values,
jumps, from a sender not in ``allow`` or spoofing a bound device id are counted by reason and skipped
(``motion.live.receiver``).

The session is written as it goes into ``out_dir`` (default ``runs/live/<time>/``, new):
``<subject>/capture.csv`` (the frames as a Live Link Face CSV, appended and flushed after every drain of the
socket: a crash or SIGKILL keeps them; ``python infer.py expressions=...`` on it gives the same params),
``<subject>/params.npz`` (``data.params``, as infer.py writes it) when the stream closes (stop, idle for
``idle_seconds``, error), ``summary.json`` at stop (``rejected`` by reason; per subject ``frames``,
``missing_frames``, ``gaps``, ``latency_ms`` p50/p99/max from receipt to params).  Stops on Ctrl-C / SIGTERM
or after ``duration`` seconds.  A status line every ``status_seconds``.  Head angles: ``head_units``,
``*_sign``, ``recenter`` as in ``motion/head2neck/cli.py``.  ``host=0.0.0.0`` listens on every interface
(docs/tools.md: what that exposes); ``allow=[192.168.1.20,10.0.0.0/24]`` accepts only those senders.

``viewer=true``: a live view at ``http://viewer_host:viewer_port/`` (default http://127.0.0.1:8765/): the
character posed by each output frame over a WebSocket, tau and the joint angles as curves
(``motion.live.viewer_server``; the first phone seen is shown).
"""
from __future__ import annotations

import json
import signal
from datetime import datetime
from pathlib import Path

from base.cli import to_dataclass
from base.errors import InputError
from base.files import atomic_folder, require_new_folder
from motion.live.config import LiveConfig
from motion.live.face_feed import FaceFeed, write_feed
from motion.live.outputs import SessionWriter, write_session
from motion.live.receiver import LiveReceiver
from motion.live.stream import StreamOptions
from motion.live.viewer_server import start_viewer
from motion.pipeline.config import InferConfig
from motion.pipeline.models import Models, load_models


def default_out_dir() -> Path:
    return Path("runs") / "live" / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")


def live_models(config: LiveConfig, announce=print) -> Models:
    """The larynx and neck models and the rig, chosen as infer.py chooses them (``motion.pipeline.models``)."""
    models = load_models(InferConfig(checkpoint=config.checkpoint, head2neck=config.head2neck, rig=config.rig),
                         announce)
    models.producers["tool"] = "motion.live"
    return models


def stream_options(config: LiveConfig) -> StreamOptions:
    return StreamOptions(config.head_units, config.signs, config.recenter, config.eta, config.max_gap_seconds,
                         config.max_lead_seconds)


def finish(receiver: LiveReceiver, out_dir: Path, eta: float) -> dict:
    """End the session: with a writer (the command), every stream closed (its params.npz) and summary.json
    written into ``out_dir``; without (tests, the benchmark), the whole session into ``out_dir`` at once."""
    extra = {"datagrams": receiver.received}
    if receiver.writer is None:
        with atomic_folder(out_dir) as staging:
            return write_session(staging, list(receiver.streams.values()), dict(receiver.rejected), eta, extra)
    receiver.close_all("stop")
    return receiver.writer.finish(dict(receiver.rejected), extra)


def run_face(config: LiveConfig, models: Models, out_dir: Path, viewer, on_frame) -> dict:
    """A webcam or a video through the face stage (``motion.live.face_feed``) instead of phones."""
    stop = {"signal": None}

    def on_signal(number, _frame):
        stop["signal"] = signal.Signals(number).name

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        feed = FaceFeed(models, config.camera, config.video, config.face_model, config.mirror, config.realtime,
                        config.eta, config.recenter, on_frame=on_frame)
        until = f"for {config.duration:g} s" if config.duration else "until the end or Ctrl-C"
        print(f"live: {feed.device} at {feed.rate[0]} fps through the face stage {until}; writing {out_dir} at the end")
        feed.run(config.duration, lambda: stop["signal"] is not None, config.status_seconds)
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        if viewer is not None:
            viewer.close()
    print(f"live: stopped ({stop['signal'] or 'end'}); {feed.received} frames read, {feed.produced} frames out, "
          f"no face in {feed.rejected['no_face']}")
    summary = write_feed(feed, out_dir, config.eta)
    print(json.dumps({"out": str(out_dir), "rejected": summary["rejected"],
                      "subjects": {k: {"frames": v["frames"], "missing_frames": v["missing_frames"],
                                       "latency_ms": v["latency_ms"]} for k, v in summary["subjects"].items()}}))
    return summary


def run(cfg) -> dict:
    config: LiveConfig = to_dataclass(cfg, LiveConfig, where="configs/live.yaml")
    out_dir = Path(config.out_dir) if config.out_dir else default_out_dir()
    require_new_folder(out_dir)  # refuse now, not after the session
    models = live_models(config)
    viewer, on_frame = None, None
    if config.viewer:
        try:
            viewer, on_frame = start_viewer(models, config.viewer_host, config.viewer_port, config.eta)
        except OSError as e:
            raise InputError(f"viewer_host={config.viewer_host} viewer_port={config.viewer_port}: cannot listen "
                             f"({e.strerror or e})") from None
        vhost, vport = viewer.address
        print(f"live: live view on http://{vhost}:{vport}/", flush=True)
    if config.camera is not None or config.video is not None:
        return run_face(config, models, out_dir, viewer, on_frame)
    try:
        receiver = LiveReceiver(models, stream_options(config), config.host, config.port, config.max_phones,
                                config.absurd_weight, on_frame=on_frame, writer=SessionWriter(out_dir, config.eta),
                                allow=config.allow, idle_seconds=config.idle_seconds)
    except OSError as e:
        if viewer is not None:
            viewer.close()
        raise InputError(f"host={config.host} port={config.port}: cannot listen ({e.strerror or e})") from None
    out_dir.mkdir(parents=True)  # the session's folder, written as it goes (not a staging folder)
    stop = {"signal": None}

    def on_signal(number, _frame):
        stop["signal"] = signal.Signals(number).name

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    host, port = receiver.address
    until = f"for {config.duration:g} s" if config.duration else "until Ctrl-C"
    print(f"live: listening on {host}:{port} (UDP, Live Link Face v6) {until}; writing {out_dir} as it goes",
          flush=True)
    failure = None
    try:
        receiver.run(config.duration, lambda: stop["signal"] is not None, config.tick_ms / 1000.0,
                     config.status_seconds)
    except Exception as e:  # a bug must not lose the session: write what was received, then fail
        failure = e
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)
        receiver.close()
        if viewer is not None:
            viewer.close()
    print(f"live: stopped ({stop['signal'] or ('error' if failure else 'duration')}); {receiver.received} "
          f"datagrams, {receiver.produced} frames out")
    summary = finish(receiver, out_dir, config.eta)
    if failure is not None:
        raise failure
    print(json.dumps({"out": str(out_dir), "rejected": summary["rejected"],
                      "subjects": {k: {"frames": v["frames"], "missing_frames": v["missing_frames"],
                                       "latency_ms": v["latency_ms"]} for k, v in summary["subjects"].items()}}))
    return summary
