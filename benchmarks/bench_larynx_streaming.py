"""Streaming speed of the expression -> larynx transformer on CPU.

    python benchmarks/bench_larynx_streaming.py [--checkpoint runs/.../last.pt | --members 5] [--far 100000]
                                                [--threads 2]

Prints:
- frames/s of the whole-sequence API (``generate``) and of the live per-frame API (``step``), B = 1;
- the per-frame cost (median over 500 frames) at frame 100, 10,000 and ``--far``, and the bytes of
  tensors the stream carries there (``state_bytes``; constant: bounded memory); the cost at ``--far`` over
  the cost at frame 100 must stay under ``FLAT_RATIO`` (bounded cost; the tests check the bounded memory);
- FaceFormer-style decoding, which reruns the model on the whole prefix at every frame
  (``generate_uncached``): its per-frame cost at prefix 100, 600 (FaceFormer's limit) and 2,000
  frames, the ratio to streaming, and the total time of a 600-frame clip both ways.
(``state_bytes`` and ``generate_uncached``: ``tests/larynx_reference.py``, shared with the tests.)

Without ``--checkpoint`` the model has the default size (``LarynxTransformerConfig``, the
``model`` group's schema) and random weights, an ensemble of ``--members`` of them (``task.members``' default);
speed does not depend on the weights.  The CPU may be shared with other
processes: figures are medians, and the load average is printed beside them.
"""
from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from timing import frames_per_second  # noqa: E402

from models.checkpoint import load_model  # noqa: E402
from models.larynx import (  # noqa: E402
    LarynxDataFields,
    LarynxEnsemble,
    LarynxTransformer,
    LarynxTransformerConfig,
)
from tests.larynx_reference import generate_uncached, state_bytes  # noqa: E402

FLAT_RATIO = 1.5  # bound on the per-frame cost far into a take over the cost at frame 100 (bounded cost)


def default_model(members: int):
    """An ensemble of ``members`` random default-size networks (one network for 1)."""
    torch.manual_seed(0)
    networks = [LarynxTransformer(LarynxTransformerConfig(), LarynxDataFields(30.0, [], 0.0, 0.01)).eval()
                for _ in range(members)]
    return networks[0] if members == 1 else LarynxEnsemble(networks).eval()


def streaming_costs(model, psi: torch.Tensor, positions: list[int], span: int = 500
                    ) -> dict[int, tuple[float, float, int]]:
    """Median wall-clock and CPU seconds per ``step()`` (the live per-frame API: encode one frame, decode it)
    over ``span`` frames from each position, and the bytes of tensors the stream holds there.

    One stream per position is first stepped up to it (untimed); the streams then take turns, one frame
    each, so that load from other processes falls on all positions alike.
    """
    streams = {p: model.stream(1) for p in positions}
    wall, cpu = {p: [] for p in positions}, {p: [] for p in positions}
    for p, stream in streams.items():
        for t in range(p):
            stream.step(psi[t % len(psi)])
    for i in range(span):
        for p, stream in streams.items():
            frame = psi[(p + i) % len(psi)]
            start, start_cpu = time.perf_counter(), time.process_time()
            stream.step(frame)
            wall[p].append(time.perf_counter() - start)
            cpu[p].append(time.process_time() - start_cpu)
    return {p: (float(np.median(wall[p])), float(np.median(cpu[p])), state_bytes(streams[p])) for p in positions}


def best_over_threads(run, threads: int) -> tuple[float, int]:
    """(seconds, threads) of the faster of 1 and ``threads`` torch threads: on a CPU shared with other
    processes a second thread can stall, and FaceFormer-style decoding should get its best case."""
    results = []
    for count in sorted({1, threads}):
        torch.set_num_threads(count)
        results.append((run(), count))
    torch.set_num_threads(threads)
    return min(results)


def recompute_cost(model, psi: torch.Tensor, prefix: int, repeats: int = 5) -> float:
    """Seconds for one FaceFormer-style frame: the model rerun on the whole prefix (median of ``repeats``)."""
    times = []
    with torch.no_grad():
        for _ in range(repeats):
            start = time.perf_counter()
            model(psi[None, :prefix])
            times.append(time.perf_counter() - start)
    return float(np.median(times))


def timed(run) -> float:
    start = time.perf_counter()
    run()
    return time.perf_counter() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", help="a larynx_transformer checkpoint (default: random default-size model)")
    parser.add_argument("--members", type=int, default=5, help="without --checkpoint: networks in the ensemble")
    parser.add_argument("--far", type=int, default=100_000, help="farthest frame whose cost is measured")
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    model = load_model(args.checkpoint, "larynx_transformer")[0] if args.checkpoint else default_model(args.members)
    members = model.config.get("members", [model.config])
    cfg = members[0]
    print(f"model: {len(members)} member(s) of d_model {cfg['d_model']}, {cfg['n_layers']} layers, {cfg['n_heads']} "
          f"heads, window {cfg['window']}, expression dilations {cfg['expression_dilations']}; "
          f"torch threads {args.threads}; load average {os.getloadavg()[0]:.2f}")
    psi = torch.rand(20_000, 55, generator=torch.Generator().manual_seed(0))

    whole, whole_cpu = frames_per_second(lambda: model.generate(psi[None]), len(psi), repeats=3, warmup=1)
    stream = model.stream(1)
    live, live_cpu = frames_per_second(lambda: [stream.step(psi[t]) for t in range(2000)], 2000, repeats=3)
    print(f"\nstreaming, B=1 (frames per wall-clock second, per CPU second):\n"
          f"  generate() {whole:8.0f} {whole_cpu:8.0f}\n  step()     {live:8.0f} {live_cpu:8.0f}")

    positions = [100, 10_000, args.far]
    costs = streaming_costs(model, psi, positions)
    print("\nper-frame cost of step(), median over 500 frames (wall clock, CPU):")
    for p in positions:
        wall, cpu, held = costs[p]
        print(f"  frame {p:>7}: {wall * 1e3:6.3f} ms {cpu * 1e3:6.3f} ms = {1 / cpu:6.0f} frames per CPU second;"
              f" stream holds {held} bytes of tensors")
    flat, flat_cpu = costs[args.far][0] / costs[100][0], costs[args.far][1] / costs[100][1]
    print(f"  cost at frame {args.far} / frame 100 = {flat:.2f} (wall clock), {flat_cpu:.2f} (CPU)")
    print(f"  target: the cost does not grow with the position, ratio < {FLAT_RATIO} (wall clock) -> "
          f"{'met' if flat < FLAT_RATIO else 'NOT met'}")

    print(f"\nFaceFormer-style full-prefix recomputation (per frame, best of 1 and {args.threads} threads):")
    for prefix in (100, 600, 2000):
        cost, threads = best_over_threads(lambda n=prefix: recompute_cost(model, psi, n), args.threads)
        print(f"  prefix {prefix:>5}: {cost * 1e3:8.2f} ms = {cost / costs[100][0]:6.1f} x streaming "
              f"({threads} thread)")
    if len(members) > 1:
        print(f"\nload average now {os.getloadavg()[0]:.2f}")
        return
    clip = psi[None, :600]
    uncached, threads = best_over_threads(lambda: timed(lambda: generate_uncached(model, clip)), args.threads)
    cached = min(timed(lambda: model.generate(clip)) for _ in range(3))
    print(f"  600-frame clip: recomputation {uncached:.2f} s ({threads} thread), streaming {cached:.3f} s, "
          f"ratio {uncached / cached:.0f} x")
    print(f"\nload average now {os.getloadavg()[0]:.2f}")


if __name__ == "__main__":
    main()
