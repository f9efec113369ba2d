"""Calibration of head -> neck to a user's recording, deciding from the recording how far to trust it (issue 58).

A recording's theta need not be a function of head orientation: in a real HACK-fitted sequence, frames whose
heads point within 2 degrees of each other carry C1-C2 rotations up to 11.5 degrees apart, the lower levels
counter-rotating as the split drifts over time.  Trained on such frames alone the network memorises the
drift and predicts the rest of the take worse than the shipped preset (issue 58: 2.54 against 2.40 deg).  So
the default calibration (``data=theta_seq``, ``data.calibrate=true``) measures before it trusts:

- the shipped presets (``default``: the in-vivo style, ``hack``: HACK's) are scored on every calibration
  frame; the better one is "the preset", its style the prior's style;
- time-blocked cross-validation: the calibration frames (in time order, files one after another) are cut
  into ``folds`` contiguous blocks; each block is held out in turn, the model trained on the other frames
  minus ``gap`` of a block on each side of it (neighbouring frames share the drift's state) and scored on it.
  Never random frames: a held-out frame's neighbours in time would carry its drift into training;
- candidates: the starting point (the preset's weights, or scratch: the in-vivo split with a zero residual),
  the share of each batch drawn from the prior (``prior_weights``) in the preset's style, and the training
  length (``steps``: every candidate is scored after each length, one run per candidate and fold);
- the held-out error of a candidate is the frame-weighted mean over the blocks of the task's joint error
  (mean per-joint angle after the exact correction); the preset's is printed beside each;
- a candidate (with its length) is eligible only if it beats the preset on every held-out block, and on
  their mean by at least ``min_gain`` of the preset's error: a gain on some blocks with a loss on another is
  what a split drifting over the take gives, and the rest of the take then loses (benchmarks/README.md,
  calibration: a 5 deg drift, 1.827 deg against the preset's 1.614 under the mean alone).  The eligible one
  with the lowest mean is kept; with none, the calibration says so and keeps the preset, untrained.
The chosen candidate is then trained on all calibration frames exactly as in the cross-validation (the same
stacked trainer, ``tasks.head2neck_stack``).  ``data.start``, ``data.prior_weight`` and ``data.steps`` fix a
choice (the cross-validation then ranges over the others); ``data.calibrate=false`` skips all of it and trains
the fixed knobs in the loop as before.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from base.errors import InputError
from data.cervical_prior import PriorConfig, sample_sequences
from models.checkpoint import load_model
from models.head2neck import Head2NeckConfig, Head2NeckMLP
from models.pretrained import pretrained_path
from tasks.head2neck_stack import FrameBank, Member, StackedMLP, StackSettings, member_errors, train_stack

PRESET_FILES = {"default": "head2neck", "hack": "head2neck_hack"}   # models/pretrained/ entries
PRESET_STYLES = {"default": "invivo", "hack": "hack"}                # the prior each was trained on
STARTS = ("default", "hack", "preset", "scratch")                    # data.start; preset = the better of the two


@dataclass
class CalibrationConfig:
    """``data.calibration``: how the cross-validation runs (module docstring)."""

    folds: int = 3                   # contiguous blocks of the calibration frames
    gap: float = 0.125               # frames left out on each side of a held-out block, as a share of a block
    steps: list[int] = field(default_factory=lambda: [25, 100, 300])      # training lengths scored
    prior_weights: list[float] = field(default_factory=lambda: [0.0, 0.5, 0.9])  # shares tried from the preset
    scratch_prior_weights: list[float] = field(default_factory=lambda: [0.0])    # shares tried from scratch
    min_gain: float = 0.01           # a candidate must beat the preset's held-out error by this share
    batch_size: int = 64             # frames a step (a few hundred frames in all: larger batches cost, not help)
    lr: float = 5.0e-4               # AdamW, after a linear warm-up; constant, so a length is a stop
    warmup_steps: int = 20
    grad_clip: float = 1.0
    prior_sequences: int = 256       # prior sequences of the preset's style to draw the prior's share from
    seed: int = 0

    def __post_init__(self) -> None:
        if int(self.folds) < 2:
            raise ValueError(f"folds={self.folds}: expected at least 2 blocks")
        if not 0 <= float(self.gap) < 0.5:
            raise ValueError(f"gap={self.gap}: expected a share of a block in [0, 0.5)")
        if not list(self.steps) or any(int(s) < 1 for s in self.steps):
            raise ValueError(f"steps={list(self.steps)}: expected one or more positive lengths")
        for name in ("prior_weights", "scratch_prior_weights"):
            if any(not 0 <= float(w) < 1 for w in getattr(self, name)):
                raise ValueError(f"{name}={list(getattr(self, name))}: expected shares in [0, 1)")
        if int(self.batch_size) < 1 or not float(self.lr) > 0 or int(self.warmup_steps) < 0:
            raise ValueError(f"batch_size={self.batch_size}, lr={self.lr}, warmup_steps={self.warmup_steps}: "
                             f"expected a positive batch and rate and a non-negative warm-up")
        if not float(self.min_gain) >= 0:
            raise ValueError(f"min_gain={self.min_gain}: expected a non-negative share")


@dataclass(frozen=True)
class Candidate:
    """A way to calibrate: where training starts, the prior's share of each batch and its style."""

    start: str                       # a preset name or "scratch"
    prior_weight: float
    style: str

    def label(self) -> str:
        share = f"prior {self.style} {self.prior_weight:g}" if self.prior_weight else "files alone"
        return f"{'from ' + self.start if self.start != 'scratch' else 'scratch'}, {share}"


@dataclass
class Choice:
    """What the calibration keeps: the model, the candidate and length (None: the preset, untrained), and the
    held-out errors behind it."""

    model: Head2NeckMLP
    candidate: Candidate | None
    steps: int
    preset: str
    preset_error: float
    error: float
    table: list[tuple[str, dict[int, float]]]


def contiguous_blocks(frames: int, folds: int) -> list[tuple[int, int]]:
    """``folds`` contiguous [start, stop) blocks covering range(frames), sizes differing by at most one."""
    if frames < 2 * folds:
        raise InputError(f"{frames} calibration frames are too few for {folds} blocks of at least 2 frames")
    edges = np.linspace(0, frames, folds + 1).round().astype(int)
    return [(int(a), int(b)) for a, b in zip(edges[:-1], edges[1:])]


def fold_frames(frames: int, block: tuple[int, int], gap: float) -> torch.Tensor:
    """Indices of the training frames of the fold holding out ``block``: every frame but the block and
    ``gap`` of its length on each side."""
    start, stop = block
    margin = int(round(gap * (stop - start)))
    index = torch.arange(frames)
    return index[(index < start - margin) | (index >= stop + margin)]


def load_preset(name: str) -> Head2NeckMLP:

    return load_model(pretrained_path(PRESET_FILES[name]), task="head2neck")[0].eval()


def prior_theta(style: str, config: CalibrationConfig, prior: PriorConfig) -> torch.Tensor:
    """Anatomical theta [N,J,3] of ``config.prior_sequences`` prior sequences in ``style`` (``prior``'s other
    settings)."""
    settings = PriorConfig(**{**prior.__dict__, "style": style})
    theta = sample_sequences(config.prior_sequences, config.seed + 1, settings).theta
    return torch.as_tensor(theta.reshape(-1, *theta.shape[2:]), dtype=torch.float32)


def candidates_for(config: CalibrationConfig, preset: str, start: str | None,
                   prior_weight: float | None) -> list[Candidate]:
    """The grid: from the preset with each of ``prior_weights``, from scratch with each of
    ``scratch_prior_weights``, in the preset's style; ``start`` / ``prior_weight`` fix that choice."""
    style = PRESET_STYLES[preset]
    grid = [Candidate(preset, float(w), style) for w in config.prior_weights]
    grid += [Candidate("scratch", float(w), style) for w in config.scratch_prior_weights]
    if start is not None:
        grid = [c for c in grid if c.start == ("scratch" if start == "scratch" else preset)]
        if not grid:
            grid = [Candidate(preset if start != "scratch" else "scratch", 0.0, style)]
    if prior_weight is not None:
        grid = sorted({Candidate(c.start, float(prior_weight), style) for c in grid}, key=lambda c: c.start)
    return grid


def starting_model(candidate: Candidate, presets: dict[str, Head2NeckMLP], model_config: Head2NeckConfig,
                   seed: int) -> Head2NeckMLP:
    if candidate.start != "scratch":
        return presets[candidate.start]
    torch.manual_seed(seed)
    return Head2NeckMLP(model_config)


def calibrate(theta: list[torch.Tensor], rig, model_config: Head2NeckConfig, task_settings: dict,
              config: CalibrationConfig, prior: PriorConfig, start: str | None = None,
              prior_weight: float | None = None, steps: int | None = None, announce=print) -> Choice:
    """Decide by time-blocked cross-validation how to calibrate to the anatomical theta sequences ``theta``
    (each [T,J,3], in time order) and train the choice on all of them (module docstring).  ``task_settings``:
    the task's ``lambda_fk``, ``lambda_rot``, ``lambda_sim``."""
    if start is not None and start not in STARTS:
        raise InputError(f"data.start={start}: expected one of {', '.join(STARTS)} (or null: chosen by the "
                         f"cross-validation)")
    frames = torch.cat(theta)
    presets = {name: load_preset(name) for name in PRESET_FILES}
    preset_errors = {name: _preset_errors(model, frames, rig) for name, model in presets.items()}
    preset = start if start in PRESET_FILES else min(preset_errors, key=lambda n: float(preset_errors[n].mean()))
    # The presets learnt nothing of these frames: their error on every frame is their held-out error.
    lengths = sorted({0, int(steps)} if steps is not None else {0, *(int(s) for s in config.steps)})
    grid = candidates_for(config, preset, start, prior_weight)
    blocks = contiguous_blocks(len(frames), int(config.folds))
    settings = StackSettings(int(config.batch_size), float(config.lr), int(config.warmup_steps),
                             float(config.grad_clip), **task_settings)
    announce(f"calibration: {len(frames)} frames in {len(blocks)} contiguous blocks of ~{len(frames) // len(blocks)};"
             f" {len(grid)} candidates x {len(blocks)} folds, lengths {lengths}")
    per_block: dict = {}
    scores = _cross_validate(frames, blocks, grid, presets, model_config, prior, config, settings, lengths, rig,
                             per_block)
    block_error = {name: float(e.mean()) for name, e in preset_errors.items()}
    preset_blocks = [float(preset_errors[preset][a:b].mean()) for a, b in blocks]
    preset_error = block_error[preset]
    table = [(f"preset {name}", {0: block_error[name]}) for name in PRESET_FILES]
    table += [(c.label(), scores[c]) for c in grid]
    _print_table(table, lengths, preset, preset_error, announce)
    announce(f"per block: preset {preset} " + " ".join(f"{e:.3f}" for e in preset_blocks) + "; " + "; ".join(
        f"{c.label()} ({n} steps) " + " ".join(f"{e:.3f}" for e in per_block[c][n])
        for c in grid for n in [min(lengths, key=lambda m, c=c: scores[c][m])]))
    # Kept only if better than the preset on every block, and on their mean by min_gain: a gain on some blocks
    # and a loss on another is what a split drifting over the take gives (the second half then loses).
    eligible = [(c, n) for c in grid for n in (lengths if steps is None else [int(steps)])
                if scores[c][n] < preset_error * (1 - float(config.min_gain))
                and all(e < p for e, p in zip(per_block[c][n], preset_blocks))]
    if not eligible:
        best, best_steps = min(((c, n) for c in grid for n in lengths if n or c.start == "scratch"),
                               key=lambda cn: scores[cn[0]][cn[1]])
        announce(f"calibration: nothing beats the preset '{preset}' on every held-out block (lowest mean: "
                 f"{best.label()}, {best_steps} steps, {scores[best][best_steps]:.3f} deg against "
                 f"{preset_error:.3f}); keeping the preset")
        return Choice(presets[preset], None, 0, preset, preset_error, preset_error, table)
    best, best_steps = min(eligible, key=lambda cn: scores[cn[0]][cn[1]])
    best_error = scores[best][best_steps]
    announce(f"calibration: keeping {best.label()}, {best_steps} steps: {best_error:.3f} deg on held-out blocks "
             f"against the preset '{preset}''s {preset_error:.3f}; training it on all {len(frames)} frames")
    model = _train_final(frames, best, best_steps, presets, model_config, prior, config, settings, rig)
    return Choice(model, best, best_steps, preset, preset_error, best_error, table)


def better_preset(frames: torch.Tensor, rig) -> str:
    """The shipped preset with the lower joint error on anatomical theta [N,J,3]."""
    return min(PRESET_FILES, key=lambda name: float(_preset_errors(load_preset(name), frames, rig).mean()))


@torch.no_grad()
def _preset_errors(model: Head2NeckMLP, frames: torch.Tensor, rig) -> torch.Tensor:
    """Per-frame joint error (deg) of a model (no training) on anatomical theta [N,J,3]."""

    bank = FrameBank.build(frames, rig, model)
    member = Member(torch.arange(len(frames)), torch.zeros(0, dtype=torch.long), 0.0, torch.arange(len(frames)))
    return member_errors(StackedMLP([model]), bank, [member], rig)[0]


def _banks(frames: torch.Tensor, grid: list[Candidate], presets: dict, model_config: Head2NeckConfig,
           prior: PriorConfig, config: CalibrationConfig, rig, seed: int) -> dict:
    """Per architecture (the presets', the scratch model's): its bank (the calibration frames, then each
    style's prior frames), the prior frames' index ranges by style, and the starting models by start."""
    styles = sorted({c.style for c in grid if c.prior_weight > 0})
    priors = {style: prior_theta(style, config, prior) for style in styles}
    groups: dict = {}
    for candidate in grid:
        model = starting_model(candidate, presets, model_config, seed)
        key = repr(model.config)
        if key not in groups:
            bank, ranges, offset = FrameBank.build(frames, rig, model), {}, len(frames)
            for style, theta in priors.items():
                bank = bank.cat(FrameBank.build(theta, rig, model))
                ranges[style] = torch.arange(offset, offset + len(theta))
                offset += len(theta)
            groups[key] = {"bank": bank, "priors": ranges, "candidates": [], "starts": []}
        groups[key]["candidates"].append(candidate)
        groups[key]["starts"].append(model)
    return groups


def _cross_validate(frames, blocks, grid, presets, model_config, prior, config, settings, lengths, rig,
                    blocks_out: dict) -> dict[Candidate, dict[int, float]]:
    """{candidate: {length: frame-weighted held-out error over the blocks}}; ``blocks_out`` gets each block's."""
    scores: dict[Candidate, dict[int, float]] = {}
    for group in _banks(frames, grid, presets, model_config, prior, config, rig, int(config.seed)).values():
        members, models, keys = [], [], []
        for candidate, model in zip(group["candidates"], group["starts"]):
            prior_index = group["priors"].get(candidate.style, torch.zeros(0, dtype=torch.long))
            for block in blocks:
                members.append(Member(fold_frames(len(frames), block, float(config.gap)), prior_index,
                                      candidate.prior_weight, torch.arange(*block)))
                models.append(model)
                keys.append(candidate)
        errors = train_stack(StackedMLP(models), group["bank"], members, rig, settings, lengths, int(config.seed))
        for candidate in group["candidates"]:
            picks = [i for i, key in enumerate(keys) if key == candidate]
            scores[candidate] = {length: float(torch.cat([errors[length][i] for i in picks]).mean())
                                 for length in lengths}
            blocks_out[candidate] = {length: [float(errors[length][i].mean()) for i in picks] for length in lengths}
    return scores


def _train_final(frames, candidate, steps, presets, model_config, prior, config, settings, rig) -> Head2NeckMLP:
    """The chosen candidate trained on every calibration frame for ``steps`` steps (the cross-validation's
    trainer, its own seed)."""
    group = next(iter(_banks(frames, [candidate], presets, model_config, prior, config, rig,
                             int(config.seed)).values()))
    prior_index = group["priors"].get(candidate.style, torch.zeros(0, dtype=torch.long))
    member = Member(torch.arange(len(frames)), prior_index, candidate.prior_weight, torch.zeros(0, dtype=torch.long))
    stack = StackedMLP(group["starts"])
    train_stack(stack, group["bank"], [member], rig, settings, [steps], int(config.seed) + 1)
    return stack.member(0)


def _print_table(table, lengths, preset, preset_error, announce) -> None:
    announce(f"held-out joint error (deg, mean over the blocks) by training length; the preset '{preset}': "
             f"{preset_error:.3f}")
    announce(f"{'candidate':40s}" + "".join(f"{s:>9d}" for s in lengths) + f"{'best/preset':>13s}")
    for label, row in table:
        cells = "".join(f"{row[s]:9.3f}" if s in row else f"{'':9s}" for s in lengths)
        announce(f"{label:40s}{cells}{min(row.values()) / preset_error:13.3f}")
