"""Head orientation -> cervical spine: batched inference speed, accuracy on a stand-in recording and on a
shifted prior, and optionally a default training run.

    python benchmarks/bench_head2neck.py [--checkpoint last.pt] [--frames 65536] [--threads 2] [--rig hack_rig.npz]
                                         [--accuracy] [--train]

Inference: ``models.head2neck.predict_theta`` (the 2x512 MLP, then the exact correction with its at most three
Gauss-Newton steps) on head orientations of the in-vivo prior, in frames per second (target >= 50,000 with 2
threads); the head orientation error and limits are checked on the output.  Without a checkpoint the MLP has
random weights of the default size (the speed does not depend on them).

``--accuracy`` (needs ``--checkpoint``): mean per-joint error (degrees) of the raw network, the network with
the correction, and the uniform, range-of-motion and in-vivo splits (each with the correction) on
- the stand-in for issue 15's held-back recording (``tests/test_head2neck.py:standin_recording``, a
  literature-based generator other than the prior; seeds 0, 1, 2), on the built-in rig and on ``--rig``;
- sequences of a prior shifted from the training one (the shifted-prior test's settings).
``--train`` runs ``python train.py task=head2neck`` with the default configuration (built-in rig) in a
temporary directory and prints its wall time and evaluation.  Both 1 and ``--threads`` threads are timed.
On a CPU shared with other jobs, OpenMP's busy-waiting threads slow multi-threaded torch down several times;
this script sets ``OMP_WAIT_POLICY=PASSIVE`` (unless already set) before importing torch, which removes that.
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
sys.path.insert(0, str(REPO / "tests"))

from timing import frames_per_second  # noqa: E402

from data.cervical_prior import PriorConfig, head_rotations, sample_sequences  # noqa: E402
from data.joint_limits import within_limits  # noqa: E402
from models.checkpoint import load_model  # noqa: E402
from models.head2neck import Head2NeckConfig, Head2NeckMLP, head_error_deg, predict_theta  # noqa: E402
from models.rig import HeadNeckModel  # noqa: E402

METHODS = ("model_raw", "model", "uniform", "rom", "invivo")
# The shifted prior of tests/test_head2neck.py::test_model_stays_no_worse_than_the_rom_split_on_a_shifted_prior.
SHIFTED = PriorConfig(range_scale_median=0.7, head_range_scale=0.8, size_dependence=0.4, coupling_scale=0.6,
                      share_sigma=0.35, kind_weights=[0.3, 0.3, 0.3, 0.1])


def inference(args) -> None:
    rig = HeadNeckModel.builtin()
    if args.checkpoint:
        model, _ = load_model(args.checkpoint, task="head2neck")
    else:
        model = Head2NeckMLP(Head2NeckConfig()).eval()
        torch.nn.init.normal_(model.mlp[-1].weight, std=0.01, generator=torch.Generator().manual_seed(0))
    sequences = sample_sequences(args.frames // 120 + 1, seed=123)
    head = head_rotations(rig, sequences.theta).reshape(-1, 3, 3)[: args.frames].contiguous()
    for threads in sorted({1, args.threads}):
        torch.set_num_threads(threads)
        wall, cpu = frames_per_second(lambda: predict_theta(model, rig, head), len(head), args.repeats)
        print(f"inference, {threads} thread(s): {wall:,.0f} frames/s wall clock, {cpu:,.0f} frames per CPU "
              f"second ({len(head)} frames per call; MLP hidden {[m.out_features for m in model.mlp[:-1:2]]} "
              f"+ correction)")
    theta = rig.to_anatomical(predict_theta(model, rig, head))
    print(f"head orientation error: max {float(head_error_deg(theta, head, rig).max()):.2e} deg; "
          f"joints inside the limits: {float(within_limits(theta).float().mean()):.4f}")


def errors(model, rig, truth: torch.Tensor) -> dict[str, torch.Tensor]:
    """Per-joint mean angular error (deg) [J] of each method on anatomical poses ``truth`` [F,8,3]."""
    from test_head2neck import split_corrected

    from base.rotations import axis_angle_to_matrix, relative_angle

    head = head_rotations(rig, truth)
    with torch.no_grad():
        outputs = {"model_raw": model(head, rig.anatomical_rest_rotations),
                   "model": rig.to_anatomical(predict_theta(model, rig, head)),
                   **{split: split_corrected(head, rig, split) for split in ("uniform", "rom", "invivo")}}
    reference = axis_angle_to_matrix(truth)
    return {name: torch.rad2deg(relative_angle(axis_angle_to_matrix(theta), reference)).mean(0)
            for name, theta in outputs.items()}


def accuracy(args) -> None:
    from test_head2neck import standin_recording

    if not args.checkpoint:
        raise SystemExit("--accuracy needs --checkpoint")
    torch.set_num_threads(1)
    model, _ = load_model(args.checkpoint, task="head2neck")
    rigs = {"built-in rig": HeadNeckModel.builtin()}
    if args.rig:
        rigs[Path(args.rig).name] = HeadNeckModel.load(args.rig)
    print("\nmean per-joint error (deg): " + "  ".join(f"{m:>9s}" for m in METHODS))
    for rig_name, rig in rigs.items():
        for seed in (0, 1, 2):
            table = errors(model, rig, standin_recording(seed))
            print(f"stand-in recording, seed {seed}, {rig_name:14s}" + "".join(f"{float(table[m].mean()):11.2f}"
                                                                         for m in METHODS))
            if seed == 0:
                print("  per joint (c7t1..oc1), model: " + " ".join(f"{float(e):.2f}" for e in table["model"])
                      + "; uniform: " + " ".join(f"{float(e):.2f}" for e in table["uniform"]))
        shifted = torch.tensor(sample_sequences(24, seed=321, config=SHIFTED).theta).reshape(-1, 8, 3)
        table = errors(model, rig, shifted)
        print(f"shifted prior (24 persons), {rig_name:14s}  " + "".join(f"{float(table[m].mean()):11.2f}"
                                                                     for m in METHODS))


def training(args) -> None:
    from base.cli import compose_config
    from tasks import loop

    cfg = compose_config("train", ["task=head2neck"])
    with tempfile.TemporaryDirectory() as run_dir:
        start = time.perf_counter()
        final = loop.fit(cfg, Path(run_dir))
        wall = time.perf_counter() - start
    print(f"default training run: {wall:.0f} s wall ({final['train_seconds']:.0f} s in the loop); "
          f"per-joint error {final['joint_err_deg']:.2f} deg (raw {final['model_raw_joint_err_deg']:.2f}) vs "
          f"uniform {final['uniform_joint_err_deg']:.2f}, ROM {final['rom_joint_err_deg']:.2f}, in-vivo split "
          f"{final['invivo_joint_err_deg']:.2f}; head error max {final['head_err_max_deg']:.1e} deg; "
          f"inside limits {final['within_limits']:.4f}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=None, help="a head2neck checkpoint (default: random weights)")
    parser.add_argument("--frames", type=int, default=65536)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rig", default=None, help="also score the stand-in on this rig file (e.g. the release's)")
    parser.add_argument("--accuracy", action="store_true", help="stand-in recording and shifted-prior errors")
    parser.add_argument("--train", action="store_true", help="also time a default training run")
    args = parser.parse_args()
    inference(args)
    if args.accuracy:
        accuracy(args)
    if args.train:
        training(args)


if __name__ == "__main__":
    main()
