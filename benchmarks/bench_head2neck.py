"""Head orientation -> cervical spine: batched inference speed, and optionally a default training run.

    python benchmarks/bench_head2neck.py [--checkpoint last.pt] [--frames 65536] [--threads 2] [--train]

Inference: ``models.head2neck.predict_theta`` (the 2x512 MLP, then the exact correction with its
at most three Gauss-Newton steps) on head orientations of the anatomical prior, in frames per second
(target >= 50,000 with 2 threads); the head orientation error and limits are checked on the output.
Without a checkpoint the MLP has random weights of the default size (the speed does not depend on
them).  ``--train`` runs ``python train.py task=head2neck`` with the default configuration (built-in
rig) in a temporary directory and prints its wall time and evaluation (target < 5 minutes).
Both 1 and ``--threads`` threads are printed.  On a CPU shared with other jobs, OpenMP's busy-waiting
threads slow multi-threaded torch down several times; this script sets ``OMP_WAIT_POLICY=PASSIVE``
(unless already set) before importing torch, which removes that.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch is imported

import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from data.cervical_prior import head_rotations, sample_sequences  # noqa: E402
from models.checkpoint import load_model  # noqa: E402
from models.head2neck import build_model, head_error_deg, predict_theta  # noqa: E402
from models.joint_limits import within_limits  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402
from timing import frames_per_second  # noqa: E402


def inference(args) -> None:
    rig = HeadNeckModel.builtin()
    if args.checkpoint:
        model, _ = load_model(args.checkpoint, task="head2neck")
    else:
        model = build_model({"rest_rotations": rig.anatomical_rest_rotations.tolist(), "hidden": [512, 512],
                             "activation": "silu", "residual_scale": 0.1}).eval()
        torch.nn.init.normal_(model.mlp[-1].weight, std=0.01, generator=torch.Generator().manual_seed(0))
    sequences = sample_sequences(args.frames // 120 + 1, seed=123)
    head = head_rotations(rig, sequences.theta)[:].reshape(-1, 3, 3)[: args.frames].contiguous()
    for threads in sorted({1, args.threads}):
        torch.set_num_threads(threads)
        wall, cpu = frames_per_second(lambda: predict_theta(model, rig, head), len(head), args.repeats)
        print(f"inference, {threads} thread(s): {wall:,.0f} frames/s wall clock, {cpu:,.0f} frames per CPU "
              f"second ({len(head)} frames per call; MLP hidden {[m.out_features for m in model.mlp[:-1:2]]} "
              f"+ correction)")
    theta = rig.to_anatomical(predict_theta(model, rig, head))
    print(f"head orientation error: max {float(head_error_deg(theta, head, rig).max()):.2e} deg; "
          f"joints inside the limits: {float(within_limits(theta).float().mean()):.4f}")


def training(args) -> None:
    import train
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(REPO / "configs"), version_base=None):
        cfg = compose("train", overrides=["task=head2neck"])
    with tempfile.TemporaryDirectory() as run_dir:
        start = time.perf_counter()
        final = train.fit(cfg, Path(run_dir))
        wall = time.perf_counter() - start
    print(f"default training run: {wall:.0f} s wall ({final['train_seconds']:.0f} s in the loop); "
          f"per-joint error {final['joint_err_deg']:.2f} deg vs uniform {final['uniform_joint_err_deg']:.2f}, "
          f"ROM {final['rom_joint_err_deg']:.2f}; head error max {final['head_err_max_deg']:.1e} deg; "
          f"inside limits {final['within_limits']:.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=None, help="a head2neck checkpoint (default: random weights)")
    parser.add_argument("--frames", type=int, default=65536)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--train", action="store_true", help="also time a default training run")
    args = parser.parse_args()
    inference(args)
    if args.train:
        training(args)


if __name__ == "__main__":
    main()
