"""Head orientation -> cervical spine: batched inference speed, accuracy on a stand-in recording and on a
shifted prior, and optionally a default training run.

    python benchmarks/bench_head2neck.py [--checkpoint last.pt] [--frames 65536] [--threads 2] [--rig hack_rig.npz]
                                         [--accuracy] [--train] [--styles] [--calibration [N ...]]
                                         [--drift [SEED ...] [--drift-share 0.3] [--drift-deg 3]] [--fixed]
                                         [--overrides KEY=VALUE ...] [--motion [SEED ...]]

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
``--styles`` (issue 46, HACK's own motion): the per-level shares (axial,
flexion, extension, lateral) of the prior's two styles, ``data.prior.style=invivo|hack``, side by side, and the
axial shares of the shipped ``default`` and ``hack`` models on a head turn; then the mean joint error of both
shipped models, the uniform and the in-vivo split on a HACK-style stand-in (``tests/hack_standin.py``: the
heads of the stand-in recording, solved per frame with E_sim, E_rot and half the axial rotation at C1-C2).
``--calibration``: the default ``data=theta_seq`` calibration on the first N frames of a HACK-style stand-in
recording (seeds 0-2 of the stand-in, 1500 frames), each run scored on a held-out session (seed 3).
``--drift`` (issue 58): the default calibration on the first half of a stand-in whose split drifts independently
of the head (:func:`drifting_standin`), scored on its second half beside both presets and the nearest-neighbour
bound (:func:`nearest_neighbour`).  ``--fixed``: also ``data.calibrate=false`` (the files alone, 2000 steps),
the advice before issue 58; ``--overrides``: settings of the default runs.  ``--motion``: the head's recent
motion (:func:`head_motion`) as extra input of the calibration's candidates, with and without.
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

import numpy as np  # noqa: E402
import torch  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from timing import frames_per_second  # noqa: E402

from base.rotations import axis_angle_to_euler, euler_to_axis_angle  # noqa: E402
from data.cervical_prior import PriorConfig, head_rotations, sample_persons, sample_sequences, segmental_euler  # noqa: E402
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


# ----------------------------------------------------------------------------- styles (issue 46)

SHARE_DIRECTIONS = (("axial", 1, 1), ("flexion", 0, 1), ("extension", 0, -1), ("lateral", 2, 1))  # drive, sign


def prior_shares(style: str, size: float = 0.5, persons: int = 400) -> dict[str, np.ndarray]:
    """Median per-level share [J] of each direction of the prior's ``style`` at drive ``size`` (no other drive)."""
    people = sample_persons(persons, np.random.default_rng(5), PriorConfig(style=style))
    out = {}
    for name, axis, sign in SHARE_DIRECTIONS:
        drives = np.zeros((persons, 1, 3))
        drives[..., axis] = sign * size
        angles = segmental_euler(drives, people)[:, 0, :, axis]                 # [N,J]
        out[name] = np.median(angles / angles.sum(-1, keepdims=True), axis=0)
    return out


def turn_heads(rig, degrees=(10.0, 20.0, 30.0, 45.0)) -> torch.Tensor:
    """Head orientations [K,3,3] of pure turns: every joint turning about its own axial axis by 1/8 of ``degrees``."""
    euler = torch.zeros(len(degrees), 8, 3)
    euler[..., 1] = torch.deg2rad(torch.tensor(degrees))[:, None] / 8
    return head_rotations(rig, euler_to_axis_angle(euler))


def axial_shares(theta: torch.Tensor) -> np.ndarray:
    """Per-level axial shares [K,J] of anatomical theta [K,J,3] (Euler ay over its sum)."""
    axial = axis_angle_to_euler(theta)[..., 1].numpy()
    return axial / axial.sum(-1, keepdims=True)


def shipped(name: str):
    from models.pretrained import NAMED, pretrained_path

    return load_model(pretrained_path(NAMED["head2neck"].get(name, "head2neck")), task="head2neck")[0]


def styles(rig_path: str | None = None) -> None:
    from hack_standin import hack_standin, solve_hack_style

    rig = HeadNeckModel.builtin()
    row = lambda label, x: print(f"{label:34s}" + "".join(f"{float(v):7.3f}" for v in x))  # noqa: E731
    print("per-level shares of the prior (median of 400 persons, drive 0.5, one direction at a time)")
    print(f"{'style / direction':34s}" + "".join(f"{n:>7s}" for n in rig.joint_names))
    shares = {style: prior_shares(style) for style in ("invivo", "hack")}
    for name, _, _ in SHARE_DIRECTIONS:
        for style in ("invivo", "hack"):
            row(f"{style:7s}{name}", shares[style][name])
    heads = turn_heads(rig)
    models = {name: shipped(name) for name in ("default", "hack")}
    print("\naxial shares on pure head turns of 10, 20, 30, 45 deg (mean over the four)")
    for name, model in models.items():
        with torch.no_grad():
            row(f"shipped {name}", axial_shares(rig.to_anatomical(predict_theta(model, rig, heads))).mean(0))
    row("HACK-style solver (E_sim, E_rot)", axial_shares(solve_hack_style(heads, rig)).mean(0))
    print("\nmean joint error (deg) on the HACK-style stand-in (500 frames each; the models' head error: max deg)")
    methods = ("default", "hack", "uniform", "invivo")
    print(f"{'seed, rig':34s}" + "".join(f"{m:>9s}" for m in methods) + f"{'head max':>10s}")
    rigs = {"built-in": rig, **({Path(rig_path).name: HeadNeckModel.load(rig_path)} if rig_path else {})}
    for rig_name, each in rigs.items():
        for seed in (0, 1, 2):
            truth = hack_standin(each, seed)
            head = head_rotations(each, truth)
            table, head_max = errors_of(models, each, truth, head)
            print(f"{f'{seed}, {rig_name}':34s}" + "".join(f"{float(table[m].mean()):9.2f}" for m in methods)
                  + f"{head_max:10.1e}")
            if seed == 0:
                for m in methods:
                    row(f"  per joint, {m}", table[m])


def errors_of(models: dict, rig, truth: torch.Tensor, head: torch.Tensor) -> tuple[dict[str, torch.Tensor], float]:
    """(per-joint mean angular error (deg) [J] of the models and the uniform / in-vivo splits on ``truth``, the
    models' largest head orientation error, deg)."""
    from test_head2neck import split_corrected

    from base.rotations import axis_angle_to_matrix, relative_angle

    with torch.no_grad():
        outputs = {name: rig.to_anatomical(predict_theta(model, rig, head)) for name, model in models.items()}
    outputs.update({split: split_corrected(head, rig, split) for split in ("uniform", "invivo")})
    reference = axis_angle_to_matrix(truth)
    head_max = max(float(head_error_deg(outputs[name], head, rig).max()) for name in models)
    return {name: torch.rad2deg(relative_angle(axis_angle_to_matrix(theta), reference)).mean(0)
            for name, theta in outputs.items()}, head_max


CALIBRATION_FRAMES = (50, 150, 300, 500, 1500)


def calibration(frames_list: list[int], fixed: bool, overrides: list[str]) -> None:
    """Error on a held-out session (seed 3) of the default ``data=theta_seq`` calibration on the first N frames
    of a HACK-style recording (seeds 0-2, 1500 frames); ``fixed``: also the files alone from scratch
    (``data.calibrate=false``, 2000 steps: the advice before issue 58)."""
    from hack_standin import hack_standin

    rig = HeadNeckModel.builtin()
    recording = torch.cat([hack_standin(rig, seed) for seed in (0, 1, 2)])
    held_out = hack_standin(rig, 3)
    print(f"calibration: data=theta_seq on the first N of {len(recording)} frames, scored on {len(held_out)} "
          f"held-out frames (mean joint error, deg); preset hack {preset_error('hack', rig, held_out):.3f}, "
          f"default {preset_error('default', rig, held_out):.3f}")
    for frames in frames_list:
        final, wall = run_theta_seq(rig, recording[:frames], held_out, overrides)
        line = f"{frames:6d} frames: default calibration {final['joint_err_deg']:.3f} ({wall:.0f} s)"
        if fixed:
            final, wall = run_theta_seq(rig, recording[:frames], held_out, ["data.calibrate=false"])
            line += f"; files alone, 2000 steps {final['joint_err_deg']:.3f} ({wall:.0f} s)"
        print(line, flush=True)


# ----------------------------------------------------------------------------- drifting stand-in (issue 58)

DRIFT_SHARE, DRIFT_DEG, DRIFT_SECONDS, DRIFT_FPS = 0.3, 3.0, 1.5, 30.0


def slow_latent(frames: int, seconds: float, fps: float, rng: np.random.Generator) -> np.ndarray:
    """A slow zero-mean latent of unit standard deviation: white noise smoothed by a Gaussian of ``seconds``."""
    width = int(round(seconds * fps))
    kernel = np.exp(-0.5 * (np.arange(-4 * width, 4 * width + 1) / width) ** 2)
    smooth = np.convolve(rng.normal(size=frames + 8 * width), kernel / kernel.sum(), "valid")[:frames]
    return (smooth - smooth.mean()) / smooth.std()


def drifting_standin(rig, seed: int = 0, share: float = DRIFT_SHARE, drift_deg: float = DRIFT_DEG,
                     seconds: float = DRIFT_SECONDS) -> torch.Tensor:
    """Anatomical theta [500,8,3] that is not a function of head orientation, as in a HACK fit (issue 58).

    The heads of ``standin_recording(seed)`` solved in HACK's style with ``share`` of the axial rotation at
    C1-C2 (``tests/hack_standin.py``; the `hack` preset learnt 0.5), replayed as four passes through the
    session at a quarter of its rate (frames 0, 4, 8, ...; then 2, 6, ...; 1, 5, ...; 3, 7, ...), so that each
    half goes through it twice and the second half revisits the first half's orientations, as a user repeats
    turns and nods;
    then a slow latent of its own (``seconds`` smoothing, 30 fps) turns C1-C2 by ``drift_deg`` (standard
    deviation) with C6-C7 .. C2-C3 counter-rotating by a fifth each, and a second latent moves flexion between
    O-C1 and the same lower levels (half the size); the exact correction then restores each frame's head.
    Independent of the head, so nothing that reads the head alone can predict it."""
    from hack_standin import hack_standin

    from base.rotations import axis_angle_to_euler, euler_to_axis_angle
    from models.head2neck import correct_to_head

    solved = hack_standin(rig, seed, share)
    solved = torch.cat([solved[offset::4] for offset in (0, 2, 1, 3)])
    rng = np.random.default_rng(1000 + seed)
    axial = np.radians(drift_deg) * slow_latent(len(solved), seconds, DRIFT_FPS, rng)
    sagittal = np.radians(drift_deg / 2) * slow_latent(len(solved), seconds * 4 / 3, DRIFT_FPS, rng)
    euler = axis_angle_to_euler(solved.double()).numpy()
    euler[:, 6, 1] += axial
    euler[:, 1:6, 1] -= axial[:, None] / 5
    euler[:, 7, 0] += sagittal
    euler[:, 1:6, 0] -= sagittal[:, None] / 5
    drifted = euler_to_axis_angle(torch.tensor(euler)).float()
    return correct_to_head(drifted, head_rotations(rig, solved), rig)


def joint_error_deg(theta: torch.Tensor, truth: torch.Tensor) -> float:
    from base.rotations import axis_angle_to_matrix, relative_angle

    return float(torch.rad2deg(relative_angle(axis_angle_to_matrix(theta), axis_angle_to_matrix(truth))).mean())


def nearest_neighbour(calibration: torch.Tensor, test: torch.Tensor, rig) -> float:
    """The nearest-neighbour bound: each test frame takes the theta of the calibration frame whose head points
    nearest to its own (angle between head orientations), corrected to its head; mean joint error (deg)."""
    from base.rotations import relative_angle
    from models.head2neck import correct_to_head

    known, wanted = head_rotations(rig, calibration), head_rotations(rig, test)
    nearest = torch.stack([relative_angle(h[None], known).argmin() for h in wanted])
    return joint_error_deg(correct_to_head(calibration[nearest], wanted, rig), test)


def run_theta_seq(rig, calibration: torch.Tensor, test: torch.Tensor, overrides: list[str]) -> tuple[dict, float]:
    """``python train.py task=head2neck data=theta_seq`` on a folder of two files (calibration frames, test
    frames; the test file held out), bone frames of the built-in rig: (eval.json, wall seconds)."""
    from base.cli import compose_config
    from data.splits import split_by_file
    from tasks import loop

    split_seed = next(s for s in range(100) if split_by_file(["a", "b"], 0.5, s)[1] == ["b"])
    with tempfile.TemporaryDirectory() as folder:
        folder = Path(folder)
        (folder / "data").mkdir()
        np.save(folder / "data" / "a.npy", rig.from_anatomical(calibration).numpy())
        np.save(folder / "data" / "b.npy", rig.from_anatomical(test).numpy())
        cfg = compose_config("train", ["task=head2neck", "data=theta_seq", f"data.path={folder / 'data'}",
                                       "data.val_fraction=0.5", f"data.split_seed={split_seed}",
                                       "trainer.progress=false", *overrides])
        start = time.perf_counter()
        final = loop.fit(cfg, folder / "run")
        return final, time.perf_counter() - start


def preset_error(name: str, rig, truth: torch.Tensor) -> float:
    with torch.no_grad():
        return joint_error_deg(rig.to_anatomical(predict_theta(shipped(name), rig, head_rotations(rig, truth))), truth)


def drift(seeds: list[int], fixed: bool, overrides: list[str], share: float = DRIFT_SHARE,
          drift_deg: float = DRIFT_DEG) -> None:
    """Default calibration on the first half of the drifting stand-in (``share`` at C1-C2, ``drift_deg``),
    scored on its second half, beside both presets and the nearest-neighbour bound; ``fixed``: also the advice
    before issue 58 (``data.calibrate=false``: the files alone, 2000 steps from scratch)."""
    rig = HeadNeckModel.builtin()
    for seed in seeds:
        truth = drifting_standin(rig, seed, share, drift_deg)
        first, second = truth[:250], truth[250:]
        print(f"\ndrifting stand-in (C1-C2 share {share:g}, drift {drift_deg:g} deg), seed {seed}: calibrated on "
              f"frames 0-249, scored on 250-499 (joint error, deg)")
        print(f"  nearest-neighbour bound {nearest_neighbour(first, second, rig):.3f}; preset hack "
              f"{preset_error('hack', rig, second):.3f}, default {preset_error('default', rig, second):.3f}",
              flush=True)
        final, wall = run_theta_seq(rig, first, second, overrides)
        print(f"  default calibration {' '.join(overrides)}: {final['joint_err_deg']:.3f} ({wall:.0f} s, head max "
              f"{final['head_err_max_deg']:.1e} deg, inside limits {final['within_limits']:.4f})", flush=True)
        if fixed:
            final, wall = run_theta_seq(rig, first, second, ["data.calibrate=false"])
            print(f"  data.calibrate=false (the files alone, 2000 steps from scratch): {final['joint_err_deg']:.3f} "
                  f"({wall:.0f} s)", flush=True)


MOTION_LAGS = (1, 5)     # frames back: the head's angular velocity and its motion over a short history
MOTION_SCALE = 30.0      # radians per frame -> about radians per second at 30 fps (the features' unit size)


def head_motion(theta: torch.Tensor, rig) -> torch.Tensor:
    """[T, 3 * len(MOTION_LAGS)]: per lag k, the world rotation vector taking the head at frame t - k to its
    orientation at t, divided by k and scaled (the first frames reuse frame 0)."""
    from base.rotations import matrix_to_axis_angle

    head = head_rotations(rig, theta)
    columns = []
    for lag in MOTION_LAGS:
        before = head[(torch.arange(len(head)) - lag).clamp(min=0)]
        columns.append(matrix_to_axis_angle(head @ before.transpose(1, 2)) * MOTION_SCALE / lag)
    return torch.cat(columns, 1)


def motion_input(seeds: list[int]) -> None:
    """Does the head's recent motion help?  The calibration's candidates without the prior (from the hack
    preset, and from scratch; 25/100/300 steps), with and without ``head_motion`` as extra input (zero-initialised
    weights, so the preset starts unchanged): held-out blocks of the first half of the drifting stand-in, and
    its second half after training on the whole first half."""
    from tasks.head2neck_calibration import (
        CalibrationConfig,
        contiguous_blocks,
        fold_frames,
        load_preset,
    )
    from tasks.head2neck_stack import FrameBank, Member, StackedMLP, StackSettings, train_stack

    config, rig = CalibrationConfig(), HeadNeckModel.builtin()
    settings = StackSettings(config.batch_size, config.lr, config.warmup_steps, config.grad_clip, 1.0, 1.0, 1e-4)
    lengths = [0, *config.steps]
    starts = {"from hack": load_preset("hack"), "scratch": Head2NeckMLP(Head2NeckConfig())}
    for seed in seeds:
        truth = drifting_standin(rig, seed)
        motion = head_motion(truth, rig)
        half = len(truth) // 2
        blocks = contiguous_blocks(half, config.folds)
        print(f"\nhead motion as input, drifting stand-in seed {seed}: joint error (deg) after {lengths} steps")
        for name, model in starts.items():
            for extra in (None, motion):
                bank = FrameBank.build(truth, rig, model, extra)
                empty = torch.zeros(0, dtype=torch.long)
                members = [Member(fold_frames(half, b, config.gap), empty, 0.0, torch.arange(*b)) for b in blocks]
                members.append(Member(torch.arange(half), empty, 0.0, torch.arange(half, len(truth))))
                width = 0 if extra is None else extra.shape[1]
                errors = train_stack(StackedMLP([model] * len(members), width), bank, members, rig, settings,
                                     lengths, config.seed)
                folds = [float(torch.cat(errors[n][:-1]).mean()) for n in lengths]
                second = [float(errors[n][-1].mean()) for n in lengths]
                label = f"{name}, {'orientation + motion' if width else 'orientation'}"
                print(f"  {label:34s} held-out blocks " + " ".join(f"{e:.3f}" for e in folds)
                      + "; second half " + " ".join(f"{e:.3f}" for e in second), flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--checkpoint", default=None, help="a head2neck checkpoint (default: random weights)")
    parser.add_argument("--frames", type=int, default=65536)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--rig", default=None, help="also score the stand-in on this rig file (e.g. the release's)")
    parser.add_argument("--accuracy", action="store_true", help="stand-in recording and shifted-prior errors")
    parser.add_argument("--train", action="store_true", help="also time a default training run")
    parser.add_argument("--styles", action="store_true", help="shares and errors of the in-vivo and HACK styles")
    parser.add_argument("--calibration", type=int, nargs="*", default=None, metavar="FRAMES",
                        help="frames of a recording against its error (none given: 50 150 300 500 1500)")
    parser.add_argument("--drift", type=int, nargs="*", default=None, metavar="SEED",
                        help="default calibration on the drifting stand-in (seeds; none given: 0 1 2)")
    parser.add_argument("--drift-share", type=float, default=DRIFT_SHARE, help="with --drift: C1-C2's axial share")
    parser.add_argument("--drift-deg", type=float, default=DRIFT_DEG, help="with --drift: the drift (deg, s.d.)")
    parser.add_argument("--overrides", nargs="*", default=[], metavar="KEY=VALUE",
                        help="with --drift, --calibration: train.py settings of the default calibration runs")
    parser.add_argument("--motion", type=int, nargs="*", default=None, metavar="SEED",
                        help="the head's recent motion as extra input, on the drifting stand-in (seeds)")
    parser.add_argument("--fixed", action="store_true", help="with --drift, --calibration: also "
                        "data.calibrate=false runs (the advice before issue 58)")
    args = parser.parse_args()
    if args.styles or args.calibration is not None or args.drift is not None or args.motion is not None:
        torch.set_num_threads(1)
        if args.styles:
            styles(args.rig)
        if args.calibration is not None:
            calibration(args.calibration or list(CALIBRATION_FRAMES), args.fixed, args.overrides)
        if args.drift is not None:
            drift(args.drift or [0, 1, 2], args.fixed, args.overrides, args.drift_share, args.drift_deg)
        if args.motion is not None:
            motion_input(args.motion or [0, 1, 2])
        return
    inference(args)
    if args.accuracy:
        accuracy(args)
    if args.train:
        training(args)


if __name__ == "__main__":
    main()
