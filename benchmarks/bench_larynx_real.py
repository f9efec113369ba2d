"""Expression -> larynx in the regime of real capture: real expressions, minutes of pairs, held-out takes.

    python benchmarks/bench_larynx_real.py [--families all] [--seeds 4] [--holdout face|any]
                                           [--swallow-spacing family|physiological|LOW,HIGH]
                                           [--out /tmp/bench_larynx_real]

psi is real: the two Live Link Face takes in ``../shared/samples/livelinkface`` (``apfel.csv``,
``facial.csv``, 30 fps) and the HACK release's ``data/bsw_list.npy`` (no rate stored; taken as 30 fps),
read where they are (the script stops with a message when they are absent).  tau is not measured on
these takes, so it comes from generator families written for this benchmark, each unlike the
project's training generator (``data.synthetic_larynx``) in lags and filters, nonlinearity, the cue
that fires a swallow and the swallow's shape, and with per-subject gains over a wide range
(``larynx_families.FAMILIES``).  Every family is a causal function of psi plus white tracker noise.  Each family fires a
swallow at nearly every cue it reads, 1.4-10.5 a minute on these takes, with refractory times of 3-5 s (the
benchmark, ``--swallow-spacing family``); people swallow about once a minute when awake
(``larynx_families.PHYSIOLOGICAL_SPACING``), and ``--swallow-spacing physiological`` gives each person a
refractory time of 35-85 s and each take a random time since their last swallow, the same cues otherwise.

Protocol per family and seed ``s``: one recording is the held-out take (``--holdout face``, the default:
a Live Link Face take, ``apfel`` for even seeds and ``facial`` for odd ones, as a user trains on some
captures and drives others of the same kind; ``--holdout any``: recording ``s mod 3``, which also holds
out ``bsw_list``, a capture of another kind: its expressions lie 10-25 standard deviations of the Live
Link Face takes' away in a dozen channels (cheekSquint, noseSneer, mouthUpperUp, browDown, mouthSmile),
extrapolation rather than a new take).  The other two are cut into contiguous pieces of about 20 s (the
*takes* of the pairs folder) and each piece is paired with the tau of :data:`SUBJECTS` subjects, one pair
file per piece and subject (``take`` = the piece, so the validation split by take never shares frames with
training).  That is 6-8k training frames.
The transformer trains with the default ``data=pairs`` config (``python train.py task=larynx_transformer
data=pairs data.path=...``, run here in-process through :func:`train_default`), and is scored streamed
on the held-out recording with each subject's style, as ``infer.py subject=...`` does.  Beside it, on
the same held-out frames: the training mean, ridge regression on a 1 s window of psi (the task's
baseline, lambda chosen on held-out training takes), and a GRU of about the transformer's parameter
count with the subject as an input, trained on the same batches (same crops and augmentation) with
the same validation-based early stopping.

Prints per family the held-out tau RMSE (UV units) of each method, mean and standard deviation over
seeds, and the transformer's ratio to ridge and to the GRU; then where the error lies: each method's RMSE on
the frames inside the held-out people's swallows and on the rest (the families know their swallows:
``larynx_families.swallow_frames``); per run, ``<out>/<family>/seed<s>/heldout.png`` plots the held-out tau beside the
predictions, and for an ensemble ``members_heldout.npz`` beside it keeps the held-out tau (``tau``
[sequences, frames]) and every member's prediction (``member``, and ``fold_member`` before the refits: [members,
sequences, frames]), so other combinations of the same members are scored without training
(``score_members.py``: the ensemble's spread over training seeds from recombined members).  The CPU may be
shared: each run is sized to a few minutes on one thread; everything is logged as it goes.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from torch import nn

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from larynx_families import (  # noqa: E402
    FAMILIES,
    FPS,
    PHYSIOLOGICAL_SPACING,
    K,
    Spacing,
    family_tau,
    mean_lr,
    swallow_frames,
    swallow_onsets,
)
from score_members import ensemble_rmse  # noqa: E402

import tasks  # noqa: E402,F401  (registers the config schemas)
from base.cli import compose_config  # noqa: E402
from base.errors import InputError  # noqa: E402
from base.files import save_npz  # noqa: E402
from base.plots import figure, save_figure  # noqa: E402
from data.expressions import read_expressions  # noqa: E402
from data.pairs import LarynxSequence, save_pair  # noqa: E402
from models.checkpoint import load_model  # noqa: E402
from models.larynx import predict_tau  # noqa: E402
from tasks.larynx_transformer import Task, fit_ridge, rmse, window_features  # noqa: E402
from tasks.loop import lr_factor, step_seeds  # noqa: E402
from tasks.members import train  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SHARED = REPO.parent / "shared"
RECORDINGS = {
    "apfel": SHARED / "samples" / "livelinkface" / "apfel.csv",
    "facial": SHARED / "samples" / "livelinkface" / "facial.csv",
    "bsw_list": SHARED / "assets" / "HACK-Model" / "data" / "bsw_list.npy",
}
SUBJECTS = 3  # tau processes (people) per recording: 8-11k training frames, as the 8,600 of issue 14
PIECE_SECONDS = 20.0


def load_recordings() -> dict[str, np.ndarray]:
    """name -> psi [T,55] at 30 fps; SystemExit naming what is missing."""
    missing = [str(p) for p in RECORDINGS.values() if not p.is_file()]
    if missing:
        raise SystemExit("the real-regime benchmarks need the real expression recordings, not found: "
                         + ", ".join(missing))
    out = {}
    for name, path in RECORDINGS.items():
        try:
            track = read_expressions(path, fps=FPS)
        except InputError as e:  # the reader's message names the file, the column and the line
            raise SystemExit(f"error: {e}") from None
        if abs(track.fps - FPS) > 1e-6:
            raise SystemExit(f"{path}: {track.fps} fps, expected {FPS}")
        out[name] = track.psi.astype(np.float32)
    return out



def plot_heldout(path: Path, heldout: list[LarynxSequence], masks: list[np.ndarray],
                 predictions: dict[str, list[np.ndarray]]) -> None:
    """One panel per held-out person (tau, each method's prediction, the person's swallow frames shaded) and
    one of the expression weights the families' cues read (jawOpen, eyeBlink), against seconds."""
    fig, axes = figure(nrows=len(heldout) + 1, figsize=(16, 2.6 * (len(heldout) + 1)), sharex=True, squeeze=False)
    seconds = np.arange(len(heldout[0])) / FPS
    for k, (sequence, mask) in enumerate(zip(heldout, masks)):
        ax = axes[k, 0]
        ax.fill_between(seconds, sequence.tau.min(), sequence.tau.max(), where=mask, color="gold", alpha=0.3,
                        label="swallow frames")
        ax.plot(seconds, sequence.tau, "k", lw=0.8, label="tau")
        for (method, series), colour in zip(predictions.items(), ("tab:red", "tab:blue", "tab:green")):
            ax.plot(seconds, series[k], color=colour, lw=0.8, label=method)
        ax.set_ylabel(f"{sequence.subject}: tau (UV)")
    axes[0, 0].legend(loc="upper right", fontsize=8)
    psi = heldout[0].psi
    axes[-1, 0].plot(seconds, psi[:, K["jawOpen"]], label="jawOpen")
    axes[-1, 0].plot(seconds, mean_lr(psi, "eyeBlink"), alpha=0.6, label="eyeBlink (L+R)/2")
    axes[-1, 0].legend(loc="upper right", fontsize=8)
    axes[-1, 0].set_xlabel(f"seconds ({heldout[0].take})")
    save_figure(fig, path, dpi=70)


def split_rmse(predictions: list[np.ndarray], sequences: list[LarynxSequence], masks: list[np.ndarray]
               ) -> tuple[float, float]:
    """RMSE over the frames inside the masks and over those outside (UV units; NaN for a side with no frame)."""
    errors = np.concatenate([p - s.tau for p, s in zip(predictions, sequences)]).astype(np.float64)
    inside = np.concatenate(masks)
    return tuple(float(np.sqrt(np.mean(e ** 2))) if len(e) else math.nan for e in (errors[inside], errors[~inside]))


# --------------------------------------------------------------------------- the pairs of one run


HOLDOUTS = ("face", "any")


def heldout_name(names: list[str], seed: int, holdout: str) -> str:
    """The recording held out at ``seed`` (see the module docstring)."""
    if holdout == "face":
        faces = [n for n in names if n != "bsw_list"]
        return faces[seed % len(faces)]
    return names[seed % len(names)]


def take_seed(name: str) -> int:
    """The ``noise_seed`` of recording ``name`` (:func:`family_tau`)."""
    return sum(map(ord, name))


def make_pairs(recordings: dict[str, np.ndarray], family: str, seed: int, folder: Path, holdout: str = "face",
               spacing: Spacing = None) -> tuple[list[LarynxSequence], list[LarynxSequence]]:
    """Write the training pair files of (family, seed) into ``folder``; returns (those pairs, the held-out
    sequences: the held-out recording with each subject's tau)."""
    names = list(recordings)
    held_out = heldout_name(names, seed, holdout)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    train_pairs, heldout = [], []
    for name, psi in recordings.items():
        taus = [family_tau(family, psi, subject, seed, take_seed(name), spacing) for subject in range(SUBJECTS)]
        if name == held_out:
            heldout += [LarynxSequence(psi, tau, FPS, f"s{subject}", f"{name}_s{subject}", take=name)
                        for subject, tau in enumerate(taus)]
            continue
        pieces = max(1, int(round(len(psi) / FPS / PIECE_SECONDS)))
        bounds = np.linspace(0, len(psi), pieces + 1).astype(int)
        for piece in range(pieces):
            cut = slice(bounds[piece], bounds[piece + 1])
            for subject, tau in enumerate(taus):
                pair = LarynxSequence(psi[cut], tau[cut], FPS, f"s{subject}", f"{name}_{piece}_s{subject}",
                                      take=f"{name}_{piece}")
                save_pair(folder / f"{pair.name}.npz", pair)
                train_pairs.append(pair)
    return train_pairs, heldout


# --------------------------------------------------------------------------- the transformer, as a user runs it

# Only what a run prints and saves; the length, validation, early stopping and best weights are the defaults
# (configs/trainer/larynx_transformer.yaml).
TRAINER = ["trainer.checkpoint_every=100000", "trainer.progress=false", "trainer.log_every=100"]


def train_default(folder: Path, run_dir: Path, seed: int, extra: list[str] = ()) -> tuple[Path, dict, Task]:
    """``python train.py task=larynx_transformer data=pairs data.path=<folder> seed=<seed>``, in-process
    (trainer.max_steps null by default: the task's choice for these data, Task.steps_for_data).  Returns (the
    checkpoint of the weights the final evaluation used, eval.json, the task)."""
    overrides = ["task=larynx_transformer", "data=pairs", f"data.path={folder}", f"seed={seed}", *TRAINER, *extra]
    cfg = compose_config("train", overrides)
    task = Task(cfg)
    shutil.rmtree(run_dir, ignore_errors=True)
    evaluation = train(cfg, run_dir)
    best = run_dir / "checkpoints" / "best.pt"
    return (best if best.is_file() else run_dir / "checkpoints" / "last.pt"), evaluation, task


# --------------------------------------------------------------------------- the GRU baseline


class GRUBaseline(nn.Module):
    """psi [B,T,55] and a subject style -> tau [B,T]: a linear input layer, one GRU layer, a linear readout."""

    def __init__(self, hidden: int, subjects: int, tau_mean: float, tau_scale: float, dropout: float):
        super().__init__()
        self.tau_mean, self.tau_scale = tau_mean, tau_scale
        self.style = nn.Embedding(subjects + 1, 16)
        self.project = nn.Linear(55 + 16, hidden)
        self.gru = nn.GRU(hidden, hidden, batch_first=True)
        self.dropout = nn.Dropout(dropout)
        self.head = nn.Linear(hidden, 1)

    def forward(self, psi: torch.Tensor, subject: torch.Tensor) -> torch.Tensor:
        style = self.style(subject)[:, None].expand(-1, psi.shape[1], -1)
        x = self.dropout(torch.tanh(self.project(torch.cat([psi, style], dim=2))))
        y, _ = self.gru(x)
        return self.tau_mean + self.tau_scale * self.head(self.dropout(y))[..., 0]


def parameter_count(model: nn.Module) -> int:
    return sum(p.numel() for p in model.parameters())


def gru_hidden_for(count: int) -> int:
    """The GRU width whose parameter count is closest to ``count``."""
    sizes = range(16, 513, 8)
    return min(sizes, key=lambda h: abs(parameter_count(GRUBaseline(h, 1, 0.0, 1.0, 0.0)) - count))


def train_gru(task: Task, cfg, hidden: int, seed: int, log) -> GRUBaseline:
    """The GRU trained on the task's own batches (crops, augmentation), with the transformer's optimiser,
    schedule, gradient clipping, validation, early stopping and best-weights selection."""
    torch.manual_seed(seed)
    model = GRUBaseline(hidden, len(task.subjects), task.tau_mean, float(task.model.tau_scale),
                        float(cfg.model.dropout))
    optimizer = torch.optim.AdamW(model.parameters(), lr=cfg.optim.lr, betas=tuple(cfg.optim.betas),
                                  weight_decay=cfg.optim.weight_decay)
    steps = task.total_steps
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: lr_factor(s, cfg.optim.warmup_steps, steps, cfg.optim.min_lr_factor))
    index = {name: i + 1 for i, name in enumerate(task.subjects)}
    best, best_state, since = math.inf, None, 0
    for step in range(steps):
        _, batch_seed = step_seeds(seed, step)
        batch = task.batch(step, torch.Generator().manual_seed(batch_seed))
        model.train()
        error = (model(batch["psi"], batch["subject"]) - batch["tau"]) / model.tau_scale
        loss = error.pow(2).mean() + task.settings.velocity_weight * (error[:, 1:] - error[:, :-1]).pow(2).mean()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), cfg.trainer.grad_clip)
        optimizer.step()
        schedule.step()
        done = step + 1
        if done % cfg.trainer.eval_every == 0 or done == steps:
            score = rmse(predict_gru(model, task.val, index), task.val)
            if score < best:
                best, best_state, since = score, {k: v.clone() for k, v in model.state_dict().items()}, 0
            else:
                since += 1
            log(f"    gru step {done}: val rmse {score:.5f} (best {best:.5f})")
            if cfg.trainer.early_stopping_patience and since >= cfg.trainer.early_stopping_patience:
                break
    model.load_state_dict(best_state)
    return model.eval()


@torch.no_grad()
def predict_gru(model: GRUBaseline, sequences: list[LarynxSequence], index: dict[str, int]) -> list[np.ndarray]:
    model.eval()
    return [model(torch.from_numpy(s.psi)[None], torch.tensor([index.get(s.subject, 0)]))[0].numpy()
            for s in sequences]


# --------------------------------------------------------------------------- one run, all runs


def run_one(recordings, family: str, seed: int, out: Path, log, extra: list[str] = (), gru: bool = True,
            holdout: str = "face", spacing: Spacing = None, training_seed: int | None = None) -> dict[str, float]:
    """Held-out RMSE of every method for (family, seed); ``training_seed``: train.py's seed when it is not
    the benchmark's (the held-out take, the people and the pairs stay those of ``seed``)."""
    work = out / family / f"seed{seed}" / ("" if training_seed is None else f"train{training_seed}")
    folder, run_dir = out / family / f"seed{seed}" / "pairs", work / "run"
    train_pairs, heldout = make_pairs(recordings, family, seed, folder, holdout, spacing)
    started = time.perf_counter()
    checkpoint, evaluation, task = train_default(folder, run_dir, seed if training_seed is None else training_seed,
                                                 list(extra))
    transformer_seconds = time.perf_counter() - started
    model = load_model(checkpoint, "larynx_transformer")[0]
    transformer = [predict_tau(model, s.psi, s.subject) for s in heldout]  # as infer.py subject=...
    # An ensemble's members alone (member 0 is the single network of the training seed: task.members=1), and the
    # ensembles of its first k members (``first<k>``, 1 < k < K: what fewer members would have scored)
    members, alone = {}, []
    tau = np.stack([s.tau for s in heldout])  # [sequences, frames]: the held-out recording with each person's tau
    for k, member in enumerate(getattr(model, "members", [])):
        alone.append([predict_tau(member, s.psi, s.subject) for s in heldout])
        members[f"member{k}"] = rmse(alone[-1], heldout)
    for k in range(2, len(alone)):
        members[f"first{k}"] = ensemble_rmse(np.asarray(alone[:k]), tau)
    # Where the members refit: each member's weights before its refit (member 0's: the network task.members=1
    # trains) and their ensemble, the ensemble without refitting, from the same run
    fold = fold_member_taus(run_dir, heldout)
    members.update({f"fold_member{k}": rmse(taus, heldout) for k, taus in enumerate(fold)})
    if fold:
        members["fold_ensemble"] = ensemble_rmse(np.asarray(fold), tau)
    if alone:  # every member's held-out tau, to score other combinations of the same runs without training
        save_npz(work / "members_heldout.npz", tau=tau, member=np.asarray(alone),
                 **({"fold_member": np.asarray(fold)} if fold else {}))
    average_style = [predict_tau(model, s.psi) for s in heldout]           # infer.py without subject
    window = int(round(task.settings.ridge_window * FPS))
    weights, lam = fit_ridge(train_pairs, window, list(task.settings.ridge_lambdas))
    ridge = [window_features(s.psi, window) @ weights for s in heldout]
    mean = float(np.concatenate([p.tau for p in train_pairs]).astype(np.float64).mean())
    started = time.perf_counter()
    cfg = compose_config("train", ["task=larynx_transformer", "data=pairs", f"data.path={folder}", *TRAINER,
                                   *extra])
    hidden = gru_hidden_for(parameter_count(model))
    gru_model = train_gru(task, cfg, hidden, seed, log) if gru else GRUBaseline(hidden, 0, mean, 1.0, 0.0)
    gru_seconds = time.perf_counter() - started
    index = {name: i + 1 for i, name in enumerate(task.subjects)} if gru else {}
    gru_predictions = predict_gru(gru_model, heldout, index) if gru else [np.full(len(s), np.nan) for s in heldout]
    means = [np.full(len(s), mean) for s in heldout]
    result = {
        "transformer": rmse(transformer, heldout), "transformer_average_style": rmse(average_style, heldout),
        "ridge": rmse(ridge, heldout), "gru": rmse(gru_predictions, heldout), "mean": rmse(means, heldout),
        "train_frames": float(sum(len(s) for s in task.train)), "val_frames": float(sum(len(s) for s in task.val)),
        "heldout_frames": float(sum(len(s) for s in heldout)), "steps": float(task.total_steps),
        "best_step": float(evaluation.get("best_step", task.total_steps)), "ridge_lambda": lam,
        "transformer_parameters": float(parameter_count(model)), "gru_hidden": float(hidden),
        "gru_parameters": float(parameter_count(gru_model)), "transformer_seconds": transformer_seconds,
        "gru_seconds": gru_seconds, **members,
    }
    # Where the error lies: inside the held-out people's swallows and outside them.
    masks = [swallow_frames(family, s.psi, int(s.subject[1:]), seed, take_seed(s.take), spacing) for s in heldout]
    result["swallow_fraction"] = float(np.concatenate(masks).mean())
    result["swallows_per_minute"] = sum(len(swallow_onsets(m)) for m in masks) / (sum(map(len, masks)) / FPS / 60)
    plot_heldout(work / "heldout.png", heldout, masks,
                 {"transformer": transformer, "ridge": ridge, **({"gru": gru_predictions} if gru else {})})
    for method, predictions in (("transformer", transformer), ("ridge", ridge), ("gru", gru_predictions),
                                ("mean", means)):
        result[f"{method}_in_swallows"], result[f"{method}_outside"] = split_rmse(predictions, heldout, masks)
    trained = "" if training_seed is None else f", training seed {training_seed}"
    log(f"  {family} seed {seed}{trained} (held out {heldout_name(list(recordings), seed, holdout)}): "
        + ", ".join(f"{k} {v:.5g}" for k, v in result.items()))
    return result


def fold_member_taus(run_dir: Path, heldout: list[LarynxSequence]) -> list[list[np.ndarray]]:
    """Where the members refit (``task.refit``, ``tasks.members``): each member's held-out tau on its weights
    before its refit (chosen on its validation fold), ``[member][sequence]``; ``[]`` without refits."""
    folders = sorted((run_dir / "members").glob("*/refit"), key=lambda f: int(f.parent.name))
    taus = []
    for refit in folders:
        checkpoints = refit.parent / "checkpoints"
        best = checkpoints / "best.pt"
        member = load_model(best if best.is_file() else checkpoints / "last.pt", "larynx_transformer")[0]
        taus.append([predict_tau(member, s.psi, s.subject) for s in heldout])
    return taus


def summarise(results: dict[str, list[dict[str, float]]]) -> str:
    methods = ("transformer", "transformer_average_style", "gru", "ridge", "mean")
    lines = [f"{'family':<12}" + "".join(f"{m:>28}" for m in methods) + f"{'tf/ridge':>16}{'tf/gru':>16}"]
    for family, runs in results.items():
        cells = []
        for m in methods:
            v = np.array([r[m] for r in runs])
            cells.append(f"{v.mean():.5f} +- {v.std():.5f}".rjust(28))
        tf = np.array([r["transformer"] for r in runs])
        to_ridge, to_gru = tf / np.array([r["ridge"] for r in runs]), tf / np.array([r["gru"] for r in runs])
        lines.append(f"{family:<12}" + "".join(cells) + f"{to_ridge.mean():>9.3f} +-{to_ridge.std():.2f}"
                     + f"{to_gru.mean():>9.3f} +-{to_gru.std():.2f}")
    lines.append("\nthe same, inside the held-out people's swallows | outside them (mean over seeds):")
    lines.append(f"{'family':<12}{'swallow frames, rate':>22}"
                 + "".join(f"{m:>24}" for m in ("transformer", "gru", "ridge", "mean")))
    for family, runs in results.items():
        cells = []
        for m in ("transformer", "gru", "ridge", "mean"):
            # nanmean: a held-out take may hold no swallow at all (--swallow-spacing physiological)
            inside, outside = (np.nanmean([r[f"{m}_{part}"] for r in runs]) for part in ("in_swallows", "outside"))
            cells.append(f"{inside:.5f} | {outside:.5f}".rjust(24))
        share = (f"{np.mean([r['swallow_fraction'] for r in runs]):.0%}, "
                 f"{np.mean([r['swallows_per_minute'] for r in runs]):.1f}/min")
        lines.append(f"{family:<12}{share:>22}" + "".join(cells))
    ensembles = {family: runs for family, runs in results.items() if all("member0" in r for r in runs)}
    if ensembles:
        lines.append("\nensembles (task.members): transformer / ridge of the ensemble and of its member 0 (the single "
                     "network of the training seed), mean +- std over the runs; the spread's ratio:")
        for family, runs in ensembles.items():
            ridge = np.array([r["ridge"] for r in runs])
            ensemble, single = np.array([r["transformer"] for r in runs]) / ridge, np.array(
                [r["member0"] for r in runs]) / ridge
            members = np.array([[r[k] for k in r if k.startswith("member")] for r in runs]) / ridge[:, None]
            lines.append(f"{family:<12} ensemble {' '.join(f'{v:.3f}' for v in ensemble)} = {ensemble.mean():.3f} +- "
                         f"{ensemble.std():.3f} (range {np.ptp(ensemble):.3f}); single "
                         f"{' '.join(f'{v:.3f}' for v in single)} = {single.mean():.3f} +- {single.std():.3f} (range "
                         f"{np.ptp(single):.3f}); spread ratio {ensemble.std() / max(single.std(), 1e-12):.2f} (std), "
                         f"{np.ptp(ensemble) / max(np.ptp(single), 1e-12):.2f} (range); every member "
                         f"{members.mean():.3f} +- {members.std():.3f}")
            if all("fold_ensemble" in r for r in runs):  # the same runs' members before their refits
                before, first = (np.array([r[k] for r in runs]) / ridge for k in ("fold_ensemble", "fold_member0"))
                lines.append(f"{'':<12} without refit: ensemble {' '.join(f'{v:.3f}' for v in before)} = "
                             f"{before.mean():.3f} +- {before.std():.3f}; member 0 (task.members=1) "
                             f"{' '.join(f'{v:.3f}' for v in first)} = {first.mean():.3f} +- {first.std():.3f}; the "
                             f"refit ensemble's spread / member 0's {ensemble.std() / max(first.std(), 1e-12):.2f}")
            for key in sorted({k for r in runs for k in r if k.startswith("first")}, key=lambda k: int(k[5:])):
                fewer = np.array([r[key] for r in runs]) / ridge
                lines.append(f"{'':<12} the first {key[5:]} members {' '.join(f'{v:.3f}' for v in fewer)} = "
                             f"{fewer.mean():.3f} +- {fewer.std():.3f} (range {np.ptp(fewer):.3f}); spread ratio "
                             f"{fewer.std() / max(single.std(), 1e-12):.2f} (std)")
    return "\n".join(lines)


def chosen_families(parser: argparse.ArgumentParser, text: str) -> list[str]:
    """``--families``: comma-separated names of FAMILIES, or all; a parser error names an unknown one."""
    families = list(FAMILIES) if text == "all" else text.split(",")
    unknown = [f for f in families if f not in FAMILIES]
    if unknown:
        parser.error(f"--families: unknown {', '.join(unknown)}; expected all or some of {', '.join(FAMILIES)}")
    return families


def swallow_spacing(parser: argparse.ArgumentParser, text: str) -> Spacing:
    """``--swallow-spacing``: family (None), physiological (:data:`PHYSIOLOGICAL_SPACING`) or LOW,HIGH seconds."""
    if text == "family":
        return None
    if text == "physiological":
        return PHYSIOLOGICAL_SPACING
    try:
        low, high = (float(v) for v in text.split(","))
    except ValueError:
        low = high = math.nan
    if not 0 < low <= high:
        parser.error(f"--swallow-spacing: {text}; expected family, physiological or LOW,HIGH seconds with "
                     "0 < LOW <= HIGH")
    return low, high


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--families", default="all", help="comma-separated names of FAMILIES, or all")
    parser.add_argument("--seeds", type=int, default=4, help="seeds 0..n-1")
    parser.add_argument("--first-seed", type=int, default=0, help="start the seeds here (experiments)")
    parser.add_argument("--holdout", choices=HOLDOUTS, default="face",
                        help="face: a Live Link Face take is held out (default); any: recording seed mod 3")
    parser.add_argument("--out", default="/tmp/bench_larynx_real", help="work folder (pairs, runs, results.json)")
    parser.add_argument("--training-seeds", default=None,
                        help="comma-separated train.py seeds, each run on every benchmark seed (its take, people "
                             "and pairs): the spread that the training seed alone causes")
    parser.add_argument("--override", action="append", default=[], help="extra train.py overrides (experiments)")
    parser.add_argument("--no-gru", action="store_true", help="skip the GRU baseline (experiments)")
    parser.add_argument("--resume", action="store_true",
                        help="keep the runs <out>/results.json holds (the same arguments' first runs) and go on")
    parser.add_argument("--swallow-spacing", default="family",
                        help="family: each family's refractory time (3-5 s; the benchmark); physiological: each "
                             f"person's drawn in {PHYSIOLOGICAL_SPACING[0]:g}-{PHYSIOLOGICAL_SPACING[1]:g} s, about "
                             "one swallow a minute; or LOW,HIGH seconds")
    args = parser.parse_args()
    torch.set_num_threads(1)
    families = chosen_families(parser, args.families)
    spacing = swallow_spacing(parser, args.swallow_spacing)
    training_seeds = [None] if args.training_seeds is None else [int(t) for t in args.training_seeds.split(",")]
    recordings = load_recordings()  # first: a missing recording stops the run before anything is written
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    log_file = open(out / "log.txt", "a")

    def log(text: str) -> None:
        print(text, flush=True)
        log_file.write(text + "\n")
        log_file.flush()

    log(f"bench_larynx_real: families {families}, seeds {args.seeds}, holdout {args.holdout}, "
        f"overrides {args.override}, swallow spacing {args.swallow_spacing}, "
        f"load average {os.getloadavg()[0]:.2f}")
    results: dict[str, list[dict[str, float]]] = {}
    if args.resume and (out / "results.json").is_file():
        results = {f: runs for f, runs in json.loads((out / "results.json").read_text()).items() if f in families}
        log(f"resuming: {', '.join(f'{f} {len(runs)} runs' for f, runs in results.items())} kept")
    for family in families:
        done = len(results.get(family, []))
        runs = [(seed, t) for seed in range(args.first_seed, args.first_seed + args.seeds) for t in training_seeds]
        for seed, training_seed in runs[done:]:
            results.setdefault(family, []).append(run_one(recordings, family, seed, out, log, args.override,
                                                          not args.no_gru, args.holdout, spacing, training_seed))
            (out / "results.json").write_text(json.dumps(results, indent=1))
    log("\nheld-out tau RMSE (UV units), mean +- std over seeds:\n" + summarise(results))


if __name__ == "__main__":
    main()
