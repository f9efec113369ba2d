"""Wall and CPU time of an ensemble's training, its members one after another against side by side.

    python benchmarks/bench_member_workers.py [--data pairs|synthetic] [--workers 2] [--rounds 2]
        [--before <checkout>] [--override key=value ...]

Runs ``python train.py task=larynx_transformer data=<data> trainer.member_workers=<1|workers>`` (a subprocess
each, ``OMP_NUM_THREADS=1``), alternating one process and ``--workers`` processes ``--rounds`` times, so that a
shared machine's load falls on both alike; with ``--before``, also ``python train.py`` of that checkout (the code
before the members shared their data and ran in parallel) with the same settings, alternating too.  ``data=pairs``
trains on 13 takes of 40 s (4 people; ``data.synthetic_larynx``, written to ``runs/bench_member_workers/pairs/``),
as a new user's first paired captures.  Prints each run's wall time and CPU time (the run and its worker
processes), and the ratios.  ``--override`` shortens the runs (e.g. ``task.most_steps=100``, a cap on the length the
task chooses, ``trainer.max_steps=100`` on synthetic); every run of one call uses the same overrides.
"""
from __future__ import annotations

import argparse
import os
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from data.pairs import LarynxSequence, save_pair  # noqa: E402
from data.synthetic_larynx import TRAINING_RANGES, make_sequence  # noqa: E402

OUT = REPO / "runs" / "bench_member_workers"
TAKES, SECONDS, PEOPLE, FPS = 13, 40.0, 4, 30.0


def write_pairs(folder: Path) -> Path:
    """13 takes of 40 s, each of one of 4 people, as pair files."""
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    for take in range(TAKES):
        person = take % PEOPLE
        made = make_sequence(person, take, int(SECONDS * FPS), FPS, seed=0, ranges=TRAINING_RANGES)
        name = f"take{take:02d}"
        save_pair(folder / f"{name}.npz", LarynxSequence(made.psi, made.tau, FPS, f"p{person}", name, take=name))
    return folder


def timed_run(checkout: Path, arguments: list[str], run_dir: Path) -> tuple[float, float]:
    """(wall seconds, CPU seconds of the run and its children) of ``python train.py <arguments>`` in ``checkout``."""
    shutil.rmtree(run_dir, ignore_errors=True)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONPATH": str(checkout)}
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    subprocess.run([sys.executable, "train.py", *arguments, f"hydra.run.dir={run_dir}"], cwd=checkout, env=env,
                   check=True, stdout=subprocess.DEVNULL)
    wall = time.perf_counter() - start
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    return wall, (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--data", choices=("pairs", "synthetic"), default="pairs")
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--before", type=Path, help="a checkout of the code before (its train.py run alternates too)")
    parser.add_argument("--override", action="append", default=[], help="train.py settings of every run")
    args = parser.parse_args()
    common = ["task=larynx_transformer", f"data={args.data}", "trainer.progress=false", *args.override]
    if args.data == "pairs":
        common.append(f"data.path={write_pairs(OUT / 'pairs')}")
    kinds = {"one process": (REPO, ["trainer.member_workers=1"]),
             f"{args.workers} processes": (REPO, [f"trainer.member_workers={args.workers}"])}
    if args.before is not None:
        kinds["before"] = (args.before.resolve(), [])
    times: dict[str, list[tuple[float, float]]] = {kind: [] for kind in kinds}
    print(f"load average at the start: {os.getloadavg()}; settings: {' '.join(common)}", flush=True)
    for round_ in range(args.rounds):
        for kind, (checkout, extra) in kinds.items():
            wall, cpu = timed_run(checkout, [*common, *extra], OUT / "run")
            times[kind].append((wall, cpu))
            print(f"round {round_ + 1}, {kind}: wall {wall:.1f} s, CPU {cpu:.1f} s, load {os.getloadavg()[0]:.1f}",
                  flush=True)
    means = {kind: np.mean(np.array(values), axis=0) for kind, values in times.items()}
    for kind, (wall, cpu) in means.items():
        print(f"{kind:<16} mean wall {wall:8.1f} s   mean CPU {cpu:8.1f} s")
    parallel = means[f"{args.workers} processes"]
    for kind in kinds:
        if not kind.endswith("processes"):
            print(f"{args.workers} processes / {kind}: wall {parallel[0] / means[kind][0]:.2f}, "
                  f"CPU {parallel[1] / means[kind][1]:.2f}")


if __name__ == "__main__":
    main()
