"""Live receiver latency over loopback: one phone at 60 fps, then four phones at once, then one phone whose
face is lost for 4 s (what that adds to the next frame).

    python benchmarks/bench_live.py [--seconds 12] [--phones 1 4] [--face-loss 4] [--checkpoint default]
                                    [--head2neck default] [--no-pin] [--repo PATH] [--direct]

The receiver writes each phone's capture.csv as it goes (as ``python -m motion.live`` does) where the code
measured does.  ``--repo``: the checkout whose receiver and sender are measured (default this one; e.g. an export of the
commit before a change, to alternate the two in one run on the same machine).  The face loss: the demo take
as a Live Link Face CSV with ``--face-loss`` seconds of lost-tracking rows from its 4th second (the sender
sends nothing for them: a gap by frame number); the next frame is the output frame completed by the first
datagram back, its latency from that datagram's receipt to the end of the flush that ran it.

Each phone is a ``python -m motion.live.send take=demo`` process (the built-in demo take as Live Link Face v6
datagrams at 60 fps, on its own timecode); the receiver (``motion.live.receiver.LiveReceiver``, the shipped
models, one torch thread) runs in this process.  Prints per run: datagrams sent and received, frames the
receiver itself dropped (refused: late, rate, ...) and frames missing by frame number (lost before the
receiver: the kernel's buffer, the network), and the receive -> params latency of the output frames (30 fps:
the larynx model's rate) p50 / p99 / max in ms, with the load average (the CPU may be shared).

The phones are other devices, not processes beside the receiver: on a machine of several CPUs the receiver is
pinned to the first and the senders to the others (``--no-pin``: all share every CPU), so what is measured is
the receiver's latency, not the senders' use of its CPU.
"""
from __future__ import annotations

import argparse
import inspect
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch


def _repo() -> Path:
    """``--repo`` (read before the imports below: they come from it), else this checkout."""
    if "--repo" in sys.argv:
        return Path(sys.argv[sys.argv.index("--repo") + 1]).resolve()
    return Path(__file__).resolve().parents[1]


REPO = _repo()
sys.path.insert(0, str(REPO))

from motion.live.cli import live_models, stream_options  # noqa: E402
from motion.live.config import LiveConfig  # noqa: E402
from motion.live.packet import VALUE_NAMES, parse  # noqa: E402
from motion.live.receiver import LiveReceiver  # noqa: E402
from motion.live.send.take import demo_as_take  # noqa: E402


def cpu_sets(pin: bool) -> tuple[set[int] | None, set[int] | None]:
    """(the receiver's CPUs, the senders' CPUs): the first CPU this process may use and the others, or
    (None, None) when not pinning or with a single CPU."""
    cpus = sorted(os.sched_getaffinity(0))
    if not pin or len(cpus) < 2:
        return None, None
    return {cpus[0]}, set(cpus[1:])


def face_loss_take(path: Path, seconds: float, start: float = 4.0) -> tuple[Path, int]:
    """The demo take as a Live Link Face CSV, ``seconds`` of it from ``start`` written as lost-tracking rows
    (``<timecode>,0``); (the file, the frame number of the first frame back)."""
    take = demo_as_take()
    lost = range(int(start * take.rate), int((start + seconds) * take.rate))
    lines = ["Timecode,BlendShapeCount," + ",".join(VALUE_NAMES)]
    for k, (frame, values) in enumerate(zip(take.frames, take.values)):
        secs, ff = divmod(int(frame), take.rate)
        code = f"{secs // 3600:02d}:{secs // 60 % 60:02d}:{secs % 60:02d}:{ff:06.3f}"
        lines.append(f"{code},0" if k in lost else f"{code},61," + ",".join(f"{float(v):.9g}" for v in values))
    path.write_text("\n".join(lines) + "\n")
    return path, int(take.frames[lost.stop])


def watch_next_frame(receiver, device: str, frame: int) -> dict:
    """Hook ``receiver`` (either version's: ``handle`` and ``flush`` looked up on the instance) to time the
    output completed by ``device``'s datagram of ``frame``: receipt -> the end of the flush that runs it."""
    seen: dict = {}
    handle, flush = receiver.handle, receiver.flush

    def watched_handle(data, received_ns, *rest):
        out = handle(data, received_ns, *rest)
        try:
            parsed = parse(data)
        except ValueError:
            return out
        if parsed.device == device and parsed.frame == frame:
            seen["received_ns"] = received_ns
        return out

    def watched_flush(*args):
        out = flush(*args)
        if "received_ns" in seen and "ms" not in seen:
            seen["ms"] = (time.perf_counter_ns() - seen["received_ns"]) / 1e6
        return out

    receiver.handle, receiver.flush = watched_handle, watched_flush
    return seen


def direct(config: LiveConfig, face_loss: float, repeats: int = 3) -> dict:
    """The receiver's own cost, without sockets or senders: each datagram of the demo take (``face_loss``
    seconds lost from its 4th second) handled and flushed in this process as it would be on arrival, timed
    from before ``handle`` to after ``flush``; ms per datagram that completes output frames (p50, p99) and for
    the first datagram back after the loss (median over ``repeats`` takes)."""
    from motion.live.packet import encode

    take = demo_as_take()
    lost = range(int(4.0 * take.rate), int((4.0 + face_loss) * take.rate))
    costs, back = [], []
    for _ in range(repeats):
        models = live_models(config, announce=lambda *_: None)
        receiver = LiveReceiver(models, stream_options(config), "127.0.0.1", 0, announce=lambda *_: None)
        try:
            for k, (frame, values) in enumerate(zip(take.frames, take.values)):
                if k in lost:
                    continue
                data = encode("device-0", "phone0", int(frame), values)
                cpu, started = time.thread_time_ns(), time.perf_counter_ns()
                produced = receiver.handle(data, started)
                receiver.flush()
                ms = ((time.perf_counter_ns() - started) / 1e6, (time.thread_time_ns() - cpu) / 1e6)
                getattr(receiver, "idle", lambda: None)()  # the ~16 ms between two datagrams are idle
                if k == lost.stop:
                    back.append(ms)
                elif produced:
                    costs.append(ms)
        finally:
            receiver.close()
    costs, back = np.asarray(costs), np.asarray(back)
    return {"p50_ms": np.percentile(costs, 50, axis=0), "p99_ms": np.percentile(costs, 99, axis=0),
            "back_ms": np.median(back, axis=0)}


def run(phones: int, seconds: float, config: LiveConfig, senders_cpus: set[int] | None = None,
        take: str = "demo", watch: int | None = None) -> dict:
    models = live_models(config, announce=lambda *_: None)
    extra = {}
    if "writer" in inspect.signature(LiveReceiver).parameters:  # issue 59 on: capture.csv written as it goes
        from motion.live.outputs import SessionWriter
        folder = Path(tempfile.mkdtemp(prefix="bench_live_"))
        extra["writer"] = SessionWriter(folder, config.eta)
        extra["idle_seconds"] = 3600.0  # a phone's sender that starts late must not expire the others
    receiver = LiveReceiver(models, stream_options(config), "127.0.0.1", 0, config.max_phones,
                            announce=lambda *_: None, **extra)
    seen = watch_next_frame(receiver, "device-0", watch) if watch is not None else {}
    port = receiver.address[1]
    loops = max(1, int(np.ceil(seconds / 12.0))) if take == "demo" else 1
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO), "PYTHONDONTWRITEBYTECODE": "1"}
    senders = [subprocess.Popen([sys.executable, "-m", "motion.live.send", f"take={take}", "host=127.0.0.1",
                                 f"port={port}", f"subject=phone{k}", f"device=device-{k}", f"loops={loops}"],
                                cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True,
                                preexec_fn=(lambda: os.sched_setaffinity(0, senders_cpus)) if senders_cpus else None)
               for k in range(phones)]
    try:
        receiver.run(None, lambda: all(p.poll() is not None for p in senders), status_seconds=0)
        receiver.run(0.5, lambda: False, status_seconds=0)  # the last datagrams in flight
    finally:
        for p in senders:
            if p.poll() is None:
                p.kill()
        receiver.close()
    for p in senders:
        if p.returncode:
            raise SystemExit(f"sender failed: {p.stderr.read()}")
    if len(receiver.streams) != phones:
        raise SystemExit(f"{len(receiver.streams)} of {phones} phones' streams open at the end; refused "
                         f"{dict(receiver.rejected)}; closed {getattr(receiver, 'closed', None)}")
    latency = np.concatenate([np.asarray(s.recorded.latency_ms) for s in receiver.streams.values()])
    if extra:
        shutil.rmtree(extra["writer"].out_dir, ignore_errors=True)
    sent = phones * 720 * loops if take == "demo" else receiver.received
    return {"phones": phones, "sent": sent, "received": receiver.received, "next_frame_ms": seen.get("ms"),
            "dropped_by_receiver": int(sum(receiver.rejected.values())),
            "missing": int(sum(s.missing for s in receiver.streams.values())),
            "output_frames": len(latency), "p50_ms": float(np.percentile(latency, 50)),
            "p99_ms": float(np.percentile(latency, 99)), "max_ms": float(latency.max())}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seconds", type=float, default=12.0, help="per run (the demo take, looped)")
    parser.add_argument("--phones", type=int, nargs="+", default=[1, 4])
    parser.add_argument("--checkpoint", default="default")
    parser.add_argument("--head2neck", default="default")
    parser.add_argument("--no-pin", action="store_true", help="receiver and senders share every CPU")
    parser.add_argument("--face-loss", type=float, default=4.0, help="seconds of lost face (0: no such run)")
    parser.add_argument("--repo", default=str(REPO), help="the checkout measured (default: this one)")
    parser.add_argument("--direct", action="store_true", help="only the receiver's own cost per datagram, "
                        "in process (no sockets, no senders): the face-loss take")
    args = parser.parse_args()
    torch.set_num_threads(1)
    receiver_cpus, senders_cpus = cpu_sets(not args.no_pin)
    if receiver_cpus:
        os.sched_setaffinity(0, receiver_cpus)
    print(f"receiver on CPUs {sorted(receiver_cpus or os.sched_getaffinity(0))}, senders on "
          f"{sorted(senders_cpus or os.sched_getaffinity(0))}")
    config = LiveConfig(checkpoint=args.checkpoint, head2neck=args.head2neck)
    print(f"code measured: {REPO}")
    if args.direct:
        r = direct(config, args.face_loss)
        print(f"direct, face lost {args.face_loss:g} s: handle + flush per datagram completing output frames, wall "
              f"(this thread's CPU): p50 {r['p50_ms'][0]:.2f} ({r['p50_ms'][1]:.2f}) ms, p99 {r['p99_ms'][0]:.2f} "
              f"({r['p99_ms'][1]:.2f}) ms; the first datagram back {r['back_ms'][0]:.2f} ({r['back_ms'][1]:.2f}) ms "
              f"(load average {os.getloadavg()[0]:.2f})")
        return
    for phones in args.phones:
        started = time.perf_counter()
        r = run(phones, args.seconds, config, senders_cpus)
        print(f"{phones} phone(s) at 60 fps, {time.perf_counter() - started:.1f} s: sent {r['sent']}, received "
              f"{r['received']}, dropped by the receiver {r['dropped_by_receiver']}, missing {r['missing']}; "
              f"{r['output_frames']} frames out, receive -> params p50 {r['p50_ms']:.2f} ms, p99 "
              f"{r['p99_ms']:.2f} ms, max {r['max_ms']:.2f} ms (load average {os.getloadavg()[0]:.2f})")

    if args.face_loss > 0:
        with tempfile.TemporaryDirectory() as folder:
            take, back = face_loss_take(Path(folder) / "face_loss.csv", args.face_loss)
            started = time.perf_counter()
            r = run(1, 12.0, config, senders_cpus, str(take), watch=back)
        next_ms = "not seen" if r["next_frame_ms"] is None else f"{r['next_frame_ms']:.2f} ms"
        print(f"1 phone, face lost {args.face_loss:g} s, {time.perf_counter() - started:.1f} s: received "
              f"{r['received']}, {r['output_frames']} frames out, receive -> params p50 {r['p50_ms']:.2f} ms, "
              f"p99 {r['p99_ms']:.2f} ms; the next frame after the loss {next_ms} "
              f"(load average {os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
