"""Forward-pass speed of the head-and-neck model beside the release's formulation, idle and under load.

    python benchmarks/bench_rig.py [--rig rig.npz] [--hack-assets ../shared/assets] [--batch 64]
        [--conditions idle,busy,pair] [--threads 1,2] [--seconds 2] [--rounds 3] [--skinning lbs]
        [--quiet-wait 60] [--no-release]

Batch of 64 frames, all 55 expressions active, random poses and tau, CPU, ``HeadNeckModel.forward``
(``models/rig/model.py``, its engine ``models/rig/engine.py``) against the release's algorithm
(``tests/reference_hack.py``: a dense 4x4 blended per vertex, float32) on the same inputs in the same run,
under three conditions:

- idle: nothing started beside it.  The machine may be shared: the CPU time other processes took during
  each measurement is printed ("others", in cores, from /proc/stat), and with ``--quiet-wait S`` each idle
  measurement first waits up to S seconds for a quiet second (others < 0.25 cores);
- busy: a busy-loop subprocess (``while True: pass``) takes one core;
- pair: a second process runs the same formulation with the same threads at the same time (its own
  figures, over the calls that ran inside our measurement's window, are printed too).

Each figure is the median over ``--rounds`` rounds (conditions and thread counts interleaved) of the
median per call over ~``--seconds`` s: frames per second of wall clock, and frames per CPU second of this
process (all its threads; below the wall figure x threads when threads wait or spin).  The end lists the
targets of issue 17 (busy: 2 threads >= 1 thread; idle: 2 threads >= 1.7 x 1 thread and >= 40 x the release
formulation) with the measured ratios, and the largest difference to the release (exactness, 1e-4 cm).
Without the release (a rig file alone, or the built-in rig) only our formulation is timed.
"""
from __future__ import annotations

import argparse
import json
import os
import select
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "tests")]

from timing import frames_per_second  # noqa: E402

from data.assets import RigData, convert  # noqa: E402
from data.expressions import EXPRESSION_NAMES  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402

QUIET_CORES = 0.25


# ----------------------------------------------------------------------------- what runs


def inputs(batch: int):
    g = torch.Generator().manual_seed(0)
    theta = (torch.rand(batch, 8, 3, generator=g) - 0.5) * 0.4
    psi = torch.rand(batch, 55, generator=g)
    tau = (torch.rand(batch, generator=g) - 0.5) * 0.1
    return theta, psi, tau, torch.ones(batch)


def formulations(rig: RigData, assets: Path | None, skinning: str) -> dict:
    """name -> callable(theta, psi, tau, eta): ours, and the release's when its assets are given."""
    model = HeadNeckModel(rig, skinning=skinning)
    out = {"ours": model}
    if assets is not None:
        from reference_hack import ReleaseReference

        out["release"] = ReleaseReference(assets / "HACK-Model", assets / "ICT-FaceKit", list(EXPRESSION_NAMES),
                                          dtype=torch.float32)
    return out


def measure(run, frames: int, threads: int, seconds: float) -> tuple[float, float]:
    """(frames/s wall, frames per CPU second) of ``run`` on ``threads`` torch threads for ~``seconds``."""
    torch.set_num_threads(threads)
    with torch.no_grad():
        start = time.perf_counter()
        run()  # warm-up, and the time of one call
        once = time.perf_counter() - start
        repeats = max(3, int(seconds / max(once, 1e-4)))
        return frames_per_second(run, frames, repeats, warmup=1)


# ----------------------------------------------------------------------------- the load on the machine


def _busy_ticks() -> int:
    """CPU ticks the whole machine has been busy (all cores; steal counts: another guest had the core)."""
    fields = [int(x) for x in Path("/proc/stat").read_text().split("\n", 1)[0].split()[1:]]
    user, nice, system, _idle, _iowait, irq, softirq, steal = fields[:8]
    return user + nice + system + irq + softirq + steal


def _process_ticks(pid: int) -> int:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except FileNotFoundError:
        return 0
    return int(fields[11]) + int(fields[12])  # utime, stime


class OthersLoad:
    """Cores used by processes other than this one and ``ours`` (pids) during a ``with`` block."""

    def __init__(self, ours: list[int]):
        self.ours = [os.getpid(), *ours]
        self.cores = float("nan")

    def __enter__(self):
        self._start = (time.perf_counter(), _busy_ticks(), sum(_process_ticks(p) for p in self.ours))
        return self

    def __exit__(self, *exc):
        wall = time.perf_counter() - self._start[0]
        busy = _busy_ticks() - self._start[1]
        own = sum(_process_ticks(p) for p in self.ours) - self._start[2]
        self.cores = max(0.0, (busy - own) / os.sysconf("SC_CLK_TCK") / wall)


def wait_for_quiet(limit: float) -> float:
    """Wait up to ``limit`` s for one second in which other processes use < QUIET_CORES; their load then."""
    deadline = time.perf_counter() + limit
    while True:
        with OthersLoad([]) as load:
            time.sleep(1.0)
        if load.cores < QUIET_CORES or time.perf_counter() > deadline:
            return load.cores


# ----------------------------------------------------------------------------- the second process (pair)


def partner_main(args) -> None:
    """Serve ``run <formulation> <threads>`` lines on stdin: call it back to back until ``stop <t0> <t1>``, then
    print a JSON line with the figures of the calls that ran inside [t0, t1] (``time.perf_counter``, the
    system-wide monotonic clock): the window in which the first process measured."""
    runs = formulations(RigData.load(args.rig), Path(args.hack_assets) if args.with_release else None, args.skinning)
    theta, psi, tau, eta = inputs(args.batch)
    print("ready", flush=True)
    for line in sys.stdin:
        words = line.split()
        if not words or words[0] == "quit":
            return
        forward, threads = runs[words[1]], int(words[2])
        torch.set_num_threads(threads)
        calls = []
        with torch.no_grad():
            while not select.select([sys.stdin], [], [], 0)[0]:
                start, start_cpu = time.perf_counter(), time.process_time()
                forward(theta, psi, tau, eta)
                calls.append((start, time.perf_counter(), time.process_time() - start_cpu))
        t0, t1 = (float(x) for x in sys.stdin.readline().split()[1:3])
        inside = [c for c in calls if c[0] >= t0 and c[1] <= t1] or [c for c in calls if c[1] > t0 and c[0] < t1]
        wall = float(np.median([c[1] - c[0] for c in inside]))
        cpu = float(np.median([c[2] for c in inside]))
        print(json.dumps({"fps": args.batch / wall, "cpu": args.batch / cpu, "calls": len(inside)}), flush=True)


class Partner:
    def __init__(self, args, rig_path: Path, with_release: bool):
        command = [sys.executable, __file__, "--partner", "--rig", str(rig_path), "--batch", str(args.batch),
                   "--skinning", args.skinning, "--hack-assets", args.hack_assets]
        if with_release:
            command.append("--with-release")
        self.process = subprocess.Popen(command, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        assert self.process.stdout.readline().strip() == "ready"

    def start(self, name: str, threads: int) -> None:
        self.process.stdin.write(f"run {name} {threads}\n")
        self.process.stdin.flush()
        time.sleep(0.5)  # its first calls (warm-up) before our window

    def stop(self, t0: float, t1: float) -> dict:
        self.process.stdin.write(f"stop {t0} {t1}\n")
        self.process.stdin.flush()
        return json.loads(self.process.stdout.readline())

    def close(self) -> None:
        self.process.stdin.write("quit\n")
        self.process.stdin.close()
        self.process.wait(timeout=60)


# ----------------------------------------------------------------------------- main


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rig", help="rig file from python -m data.assets (default: convert --hack-assets)")
    parser.add_argument("--hack-assets", default=str(REPO.parent / "shared" / "assets"),
                        help="folder with HACK-Model/ and ICT-FaceKit/ (the release formulation, and the rig)")
    parser.add_argument("--batch", type=int, default=64)
    parser.add_argument("--conditions", default="idle,busy,pair")
    parser.add_argument("--threads", default="1,2")
    parser.add_argument("--seconds", type=float, default=2.0, help="per measurement")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--skinning", default="lbs", choices=["lbs", "dqs"])
    parser.add_argument("--quiet-wait", type=float, default=0.0,
                        help="before each idle measurement wait up to this many s for a quiet second")
    parser.add_argument("--no-release", action="store_true", help="time our formulation only")
    parser.add_argument("--partner", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--with-release", action="store_true", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.partner:
        return partner_main(args)

    assets = Path(args.hack_assets)
    have_release = (assets / "HACK-Model" / "model").is_dir() and (assets / "ICT-FaceKit").is_dir()
    with tempfile.TemporaryDirectory() as tmp:
        if args.rig:
            rig_path = Path(args.rig)
        elif have_release:
            rig_path = Path(tmp) / "rig.npz"
            convert(assets / "HACK-Model", assets / "ICT-FaceKit", rig_path)
        else:
            rig_path = Path(tmp) / "builtin.npz"
            HeadNeckModel.builtin().rig.save(rig_path)
            print("real release not found: benchmarking the built-in rig")
        rig = RigData.load(rig_path)
        with_release = have_release and not args.no_release and rig.template.shape[0] == 14062
        run(args, rig, rig_path, assets if with_release else None)


def run(args, rig: RigData, rig_path: Path, assets: Path | None) -> None:
    runs = formulations(rig, assets, args.skinning)
    theta, psi, tau, eta = inputs(args.batch)
    threads_list = [int(t) for t in args.threads.split(",")]
    conditions = args.conditions.split(",")
    print(f"batch {args.batch}, {rig.template.shape[0]} vertices, 55 expressions, skinning {args.skinning}, "
          f"{os.cpu_count()} CPUs, torch {torch.__version__}")
    error = None
    if "release" in runs:
        with torch.no_grad():
            error = float((runs["ours"](theta, psi, tau, eta).double()
                           - runs["release"](theta, psi, tau, eta).double()).abs().max())
    partner = Partner(args, rig_path, "release" in runs) if "pair" in conditions else None
    results: dict = {}
    try:
        for _ in range(args.rounds):
            for condition in conditions:
                busy = None
                if condition == "busy":
                    busy = subprocess.Popen([sys.executable, "-c", "while True: pass"])
                    time.sleep(0.3)
                try:
                    for name, forward in runs.items():
                        for threads in threads_list:
                            if condition == "idle" and args.quiet_wait > 0:
                                wait_for_quiet(args.quiet_wait)
                            seconds = args.seconds * (1.5 if name == "release" else 1.0)
                            paired = partner is not None and condition == "pair"
                            if paired:
                                partner.start(name, threads)
                            helpers = [p.pid for p in (busy, partner.process if partner else None) if p]
                            t0 = time.perf_counter()
                            with OthersLoad(helpers) as load:
                                fps, cpu = measure(lambda f=forward: f(theta, psi, tau, eta), args.batch, threads,
                                                   seconds)
                            other = partner.stop(t0, time.perf_counter()) if paired else None
                            results.setdefault((condition, name, threads), []).append((fps, cpu, load.cores, other))
                finally:
                    if busy is not None:
                        busy.kill()
                        busy.wait()
    finally:
        if partner is not None:
            partner.close()
    report(results, conditions, list(runs), threads_list, error)


def report(results: dict, conditions, names, threads_list, error) -> None:
    def median(key, k):
        values = [r[k] for r in results.get(key, [])]
        return float(np.median(values)) if values else float("nan")

    print(f"\n{'condition':<9} {'formulation':<11} {'threads':>7} {'frames/s':>10} {'frames/CPU-s':>13} "
          f"{'others (cores)':>15}  second process (pair)")
    for condition in conditions:
        for name in names:
            for threads in threads_list:
                key = (condition, name, threads)
                pair = ""
                others = [r[3] for r in results.get(key, []) if r[3] is not None]
                if others:
                    pair = (f"{np.median([o['fps'] for o in others]):,.0f} f/s, "
                            f"{np.median([o['cpu'] for o in others]):,.0f} f/CPU-s")
                print(f"{condition:<9} {name:<11} {threads:>7} {median(key, 0):>10,.0f} {median(key, 1):>13,.0f} "
                      f"{median(key, 2):>15.2f}  {pair}")
    fps = {key: median(key, 0) for key in results}
    print("\ntargets (issue 17):")

    def ratio(a, b, target, what):
        if a in fps and b in fps:
            value = fps[a] / fps[b]
            verdict = "(no target)" if target is None else (
                f"(target >= {target}) {'met' if value >= target else 'MISSED'}")
            print(f"  {what}: {value:.2f} {verdict}")

    ratio(("busy", "ours", 2), ("busy", "ours", 1), 1.0, "one busy core, ours 2 threads / 1 thread")
    ratio(("idle", "ours", 2), ("idle", "ours", 1), 1.7, "idle, ours 2 threads / 1 thread")
    ratio(("idle", "ours", 2), ("idle", "release", 2), 40, "idle, ours / release, 2 threads each")
    ratio(("idle", "ours", 1), ("idle", "release", 1), 40, "idle, ours / release, 1 thread each")
    ratio(("pair", "ours", 2), ("pair", "ours", 1), None, "pair of processes, ours 2 threads / 1 thread")
    if error is not None:
        print(f"  largest difference to the release formulation: {error:.2e} cm (target <= 1e-4)")


if __name__ == "__main__":
    main()
