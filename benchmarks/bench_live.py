"""Live receiver latency over loopback: one phone at 60 fps, then four phones at once.

    python benchmarks/bench_live.py [--seconds 12] [--phones 1 4] [--checkpoint default] [--head2neck default]
                                    [--no-pin]

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
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from motion.live.cli import live_models, stream_options  # noqa: E402
from motion.live.config import LiveConfig  # noqa: E402
from motion.live.receiver import LiveReceiver  # noqa: E402


def cpu_sets(pin: bool) -> tuple[set[int] | None, set[int] | None]:
    """(the receiver's CPUs, the senders' CPUs): the first CPU this process may use and the others, or
    (None, None) when not pinning or with a single CPU."""
    cpus = sorted(os.sched_getaffinity(0))
    if not pin or len(cpus) < 2:
        return None, None
    return {cpus[0]}, set(cpus[1:])


def run(phones: int, seconds: float, config: LiveConfig, senders_cpus: set[int] | None = None) -> dict:
    models = live_models(config, announce=lambda *_: None)
    receiver = LiveReceiver(models, stream_options(config), "127.0.0.1", 0, config.max_phones,
                            announce=lambda *_: None)
    port = receiver.address[1]
    loops = max(1, int(np.ceil(seconds / 12.0)))
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    senders = [subprocess.Popen([sys.executable, "-m", "motion.live.send", "take=demo", "host=127.0.0.1",
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
    latency = np.concatenate([np.asarray(s.recorded.latency_ms) for s in receiver.streams.values()])
    sent = phones * 720 * loops
    return {"phones": phones, "sent": sent, "received": receiver.received,
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
    args = parser.parse_args()
    torch.set_num_threads(1)
    receiver_cpus, senders_cpus = cpu_sets(not args.no_pin)
    if receiver_cpus:
        os.sched_setaffinity(0, receiver_cpus)
    print(f"receiver on CPUs {sorted(receiver_cpus or os.sched_getaffinity(0))}, senders on "
          f"{sorted(senders_cpus or os.sched_getaffinity(0))}")
    config = LiveConfig(checkpoint=args.checkpoint, head2neck=args.head2neck)
    for phones in args.phones:
        started = time.perf_counter()
        r = run(phones, args.seconds, config, senders_cpus)
        print(f"{phones} phone(s) at 60 fps, {time.perf_counter() - started:.1f} s: sent {r['sent']}, received "
              f"{r['received']}, dropped by the receiver {r['dropped_by_receiver']}, missing {r['missing']}; "
              f"{r['output_frames']} frames out, receive -> params p50 {r['p50_ms']:.2f} ms, p99 "
              f"{r['p99_ms']:.2f} ms, max {r['max_ms']:.2f} ms (load average {os.getloadavg()[0]:.2f})")


if __name__ == "__main__":
    main()
