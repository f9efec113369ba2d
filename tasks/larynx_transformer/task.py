"""The training task of the expression -> larynx transformer: its model, batches, loss and evaluation.

Training: random crops of ``task.crop`` frames (starting anywhere, between frames too: psi and tau are
interpolated).  Besides AdamW's weight decay and dropout, a group lasso on the expression projection
(``task.input_sparsity``) shrinks the input weights of the expression channels tau does not follow: with a few
recordings many channels co-vary with tau by chance, and a new take moves them elsewhere.  The loss is the MSE of
normalised tau plus ``velocity_weight`` times the MSE of its frame differences.

Length of training: with ``trainer.max_steps`` null the task chooses it from the data
(:meth:`Task.max_steps`: ``task.epochs`` passes over the training frames, within
``[task.min_steps, task.max_steps]``); validation (``evaluate``) returns ``val_loss``, the streamed
validation RMSE, for early stopping and best-checkpoint selection.

Starting point: random weights, or with ``task.init_from`` another run's (``pretrained``: the shipped model,
trained on ``data=synthetic``; or a checkpoint path), all but the per-subject styles, which start at that
model's average person (:func:`warm_start`).

Evaluation: streamed tau RMSE on the validation sequences, beside two baselines fitted on the training data
(:mod:`.baselines`): ridge regression on a causal window of ``ridge_window`` seconds of psi and the training mean.
"""
from __future__ import annotations

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from base.cli import to_dataclass
from base.errors import InputError
from data.pairs import LarynxSequence
from models.checkpoint import load_checkpoint
from models.larynx import (
    SIZES,
    LarynxTransformerConfig,
    build_member,
    ensemble_of,
    removed_options,
    transfer_weights,
)
from models.pretrained import default_checkpoint

from .baselines import fit_ridge, rmse, window_features
from .config import LarynxTaskConfig
from .data import crop_for, load_sequences, usable_sequences


def member_weights(state: dict, member: int) -> tuple[dict, dict]:
    """(model_config, weights) of one network of a checkpoint: itself, or of an ensemble its member
    ``member`` modulo their number."""
    config, weights = state["model_config"], state["model"]
    if "members" not in config:
        return config, weights
    k = member % len(config["members"])
    prefix = f"members.{k}."
    return config["members"][k], {name[len(prefix):]: v for name, v in weights.items() if name.startswith(prefix)}


def warm_start(model, init_from: str, member: int = 0) -> None:
    """Start ``model`` from the weights of ``init_from`` (``task.init_from``): a checkpoint path, or
    ``pretrained`` for the shipped model; of an ensemble, member ``member`` starts from its member of that
    number (:func:`member_weights`).  The per-subject styles start from that model's average person
    (:func:`models.larynx.transfer_weights`).  InputError for a checkpoint of another task, of other model
    sizes or of an option this version removed; a note when it was trained at another frame rate (its filters
    are in frames)."""
    path = default_checkpoint("larynx_transformer") if init_from == "pretrained" else init_from
    try:
        state = load_checkpoint(path, "larynx_transformer")
    except InputError as e:
        raise InputError(f"task.init_from={init_from}: {e}") from None
    source_config, source = member_weights(state, member)
    state = {"model_config": source_config, "model": source}
    removed = removed_options(state["model_config"])
    if removed:
        raise InputError(f"task.init_from={init_from}: {path} was trained with {', '.join(removed)}, removed in "
                         f"this version: its weights do not fit this model")
    try:
        transfer_weights(model, state["model"])
    except ValueError as e:
        sizes = state["model_config"]
        differ = [f"model.{k}={sizes[k]}" for k in SIZES if k in sizes and sizes[k] != model.config[k]]
        hint = f"; it was trained with {', '.join(differ)}" if differ else ""
        raise InputError(f"task.init_from={init_from}: {path} does not fit this model: {e}{hint}") from None
    fps, source_fps = model.fps, float(state["model_config"].get("fps", model.fps))
    if source_fps != fps:
        print(f"larynx_transformer: task.init_from={init_from} was trained at {source_fps:g} fps, these data are "
              f"at {fps:g} fps: its filters, counted in frames, start at {source_fps / fps:.2f} times its durations")


def combine_members(checkpoints: list[dict], cfg: DictConfig) -> dict:
    """The ensemble's checkpoint entries (``tasks.members``): ``model_config`` and ``model`` of the
    :class:`~models.larynx.LarynxEnsemble` of the members' weights (their subject tables joined)."""
    members = []
    for state in checkpoints:
        member = build_member(state["model_config"])
        member.load_state_dict(state["model"])
        members.append(member)
    ensemble = ensemble_of(members)
    return {"model_config": ensemble.config, "model": ensemble.state_dict()}


def refits(cfg: DictConfig) -> bool:
    """Whether the members refit on all the data after their folds chose their lengths (``tasks.members``):
    ``task.refit`` on ``data=pairs`` (``data=synthetic`` validates on people of its own, not on training data)."""
    return bool(cfg.task.get("refit", False)) and cfg.data.kind == "pairs"


def evaluate_ensemble(cfg: DictConfig, ensemble) -> dict[str, float]:
    """The ensemble's own validation metrics where its members share one validation set (``data=synthetic``);
    ``{}`` on ``data=pairs``, where each member validates on another fold that the others trained on."""
    if cfg.data.kind != "synthetic":
        return {}
    task = Task(cfg)
    task.model = ensemble.eval()
    with torch.no_grad():
        return task.evaluate(final=True)


class Task:
    """See the module docstring; the protocol is in ``tasks/__init__.py``."""

    def __init__(self, cfg: DictConfig):
        self.cfg = cfg
        self.settings: LarynxTaskConfig = to_dataclass(cfg.task, LarynxTaskConfig, where="task")
        sizes: LarynxTransformerConfig = to_dataclass(cfg.model, LarynxTransformerConfig, where="model")
        self.fps = float(cfg.data.fps)
        crop = int(self.settings.crop)
        if crop <= sizes.window:
            raise InputError(f"task.crop ({crop}) must exceed model.window ({sizes.window}) so training "
                             f"sees full attention windows")
        self.member = int(self.settings.member or 0)  # which member of the ensemble this task trains
        train, self.val = load_sequences(cfg.data, self.member, int(self.settings.members))
        if self.settings.refit_steps is not None:  # a member's refit (tasks.members): its fold is training data too
            if cfg.data.kind != "pairs":
                raise InputError(f"task.refit_steps={self.settings.refit_steps}: a refit trains on the validation "
                                 f"takes of data=pairs; data={cfg.data.kind} validates on data of its own")
            train = train + self.val
        self.crop = crop = crop_for(train, crop, sizes.window)  # frames per training crop
        self.train = usable_sequences(train, crop)  # the model, its normalisation and the baselines see these
        all_tau = np.concatenate([s.tau for s in self.train]).astype(np.float64)
        self.subjects = sorted({s.subject for s in self.train if s.subject is not None})
        self.tau_mean = float(all_tau.mean())
        self._model_config = {
            **OmegaConf.to_container(OmegaConf.structured(sizes), resolve=True), "fps": self.fps,
            "subjects": self.subjects, "tau_mean": self.tau_mean, "tau_scale": float(max(all_tau.std(), 1e-6)),
        }
        self.model = build_member(self._model_config)
        if self.settings.init_from:
            warm_start(self.model, self.settings.init_from, self.member)

        # Training crops are gathered (and interpolated, see batch) from one concatenated array.
        self.psi = torch.from_numpy(np.concatenate([s.psi for s in self.train]))
        self.tau = torch.from_numpy(np.concatenate([s.tau for s in self.train]))
        lengths = torch.tensor([len(s) for s in self.train])
        self.starts = torch.cat([torch.zeros(1, dtype=torch.long), lengths.cumsum(0)[:-1]])
        self.lengths = lengths
        self.crop_weights = (lengths - crop + 1).double()  # each sequence as often as it has crop positions
        self.seq_subject = torch.tensor([self.model.subject_index(s.subject) for s in self.train])
        self._baselines: dict[str, float] | None = None
        trainer_steps = cfg.trainer.get("max_steps") if "trainer" in cfg else None
        self.total_steps = int(trainer_steps) if trainer_steps else self.max_steps()

    def model_config(self) -> dict:
        return self._model_config

    @property
    def device(self) -> torch.device:
        """Where the model is (and where :meth:`predict` decodes)."""
        return next(self.model.parameters()).device

    def to(self, device: torch.device) -> Task:
        """Move the model to ``device`` (tasks/__init__.py).  The training arrays stay on the CPU: ``batch``
        gathers crops there from a CPU generator and train.py moves each batch; ``predict`` sends the
        validation expressions to the model's device and brings the predictions back."""
        self.model.to(device)
        return self

    def max_steps(self) -> int:
        """Training steps for these data: ``task.epochs`` passes over the training frames, within
        ``[task.min_steps, task.max_steps]`` (used when ``trainer.max_steps`` is null)."""
        s = self.settings
        frames = float(sum(len(sequence) for sequence in self.train))
        steps = s.epochs * frames / (s.batch_size * self.crop)
        return int(min(s.max_steps, max(s.min_steps, round(steps))))

    # ------------------------------------------------------------------ training
    # The random stream of a batch is fixed: a batch seed gives the crops it gave in every earlier version, so
    # draws that no option uses any more are still made (and dropped) where they were.

    def _positions(self, size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """Source positions [B,crop] (float, frames into the concatenated training arrays) of ``size`` crops,
        each starting anywhere in its sequence, between frames too, and each crop's sequence [B]."""
        sequence = torch.multinomial(self.crop_weights, size, replacement=True, generator=generator)
        for _ in range(3):  # a crop's rate, and the period and phase of its modulation
            torch.rand(size, 1, generator=generator, dtype=torch.float64)
        offsets = torch.arange(self.crop, dtype=torch.float64)[None]  # [1,crop]
        last = (self.lengths[sequence] - 1).double()
        start = torch.rand(size, generator=generator, dtype=torch.float64) * (last - offsets[:, -1])
        return self.starts[sequence].double()[:, None] + start[:, None] + offsets, sequence

    def batch(self, step: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Random crops psi [B,crop,55] and tau [B,crop] of training sequences, and their styles subject [B]
        (the unknown subject's for a share ``task.style_dropout`` of the crops)."""
        size = int(self.settings.batch_size)
        positions, sequence = self._positions(size, generator)
        low = positions.floor().long()
        high = torch.minimum(low + 1, (self.starts[sequence] + self.lengths[sequence] - 1)[:, None])
        frac = (positions - low.double()).float()
        psi = torch.lerp(self.psi[low], self.psi[high], frac[..., None])
        tau = torch.lerp(self.tau[low], self.tau[high], frac)
        channels = (size, 1, psi.shape[2])
        torch.randn(channels, generator=generator)  # a gain, an offset and a dropout per expression channel
        torch.randn(channels, generator=generator)
        torch.rand(channels, generator=generator)
        psi = psi.clamp(0.0, 1.0)  # expression weights are in [0, 1]
        subject = self.seq_subject[sequence]
        dropped = torch.rand(size, generator=generator) < self.settings.style_dropout
        return {"psi": psi, "tau": tau, "subject": torch.where(dropped, torch.zeros_like(subject), subject)}

    def loss(self, batch: dict[str, torch.Tensor], step: int) -> tuple[torch.Tensor, dict[str, float]]:
        """MSE of normalised tau + ``velocity_weight`` * MSE of its frame differences + the group lasso of
        ``input_sparsity`` over the expression channels' input weights."""
        model = self.model
        sparsity = self.settings.input_sparsity * model.expression.project.weight.norm(dim=0).sum()  # weight [d,55]
        error = (model(batch["psi"], batch["subject"]) - batch["tau"]) / model.tau_scale
        mse = error.pow(2).mean()
        loss = mse + self.settings.velocity_weight * (error[:, 1:] - error[:, :-1]).pow(2).mean() + sparsity
        return loss, {"loss": loss.item(), "mse": mse.item()}

    # ------------------------------------------------------------------ evaluation

    def predict(self, sequences: list[LarynxSequence]) -> list[np.ndarray]:
        """Autoregressive (streamed) tau for each sequence, batched: shorter ones are padded at the end."""
        out = []
        batch = int(self.settings.eval_batch)
        for first in range(0, len(sequences), batch):
            group = sequences[first:first + batch]
            length = max(len(s) for s in group)
            psi = np.stack([np.concatenate([s.psi, np.repeat(s.psi[-1:], length - len(s), 0)]) for s in group])
            subject = torch.tensor([self._style_index(s) for s in group], device=self.device)
            tau = self.model.generate(torch.from_numpy(psi).to(self.device), subject).cpu().numpy()
            out += [tau[i, :len(s)] for i, s in enumerate(group)]  # causal: padding cannot change these
        return out

    def _style_index(self, sequence: LarynxSequence) -> int:
        """Style of a validation sequence: its subject's if seen in training, else the average style."""
        return self.model.subject_index(sequence.subject) if sequence.subject in self.subjects else 0

    def baselines(self) -> dict[str, float]:
        """Validation RMSE of ridge regression on a window of psi and of the training mean (computed once),
        over all validation sequences and over those of known and of new subjects."""
        if self._baselines is None:
            window = max(1, int(round(self.settings.ridge_window * self.fps)))
            weights, lam = fit_ridge(self.train, window, list(self.settings.ridge_lambdas))
            self._ridge = [window_features(s.psi, window) @ weights for s in self.val]
            mean = [np.full(len(s), self.tau_mean) for s in self.val]
            self._baselines = {"ridge_rmse": rmse(self._ridge, self.val), "mean_rmse": rmse(mean, self.val),
                               "ridge_lambda": lam, "ridge_window_frames": float(window)}
            for group, members in self._groups().items():
                self._baselines[f"ridge_rmse_{group}"] = rmse([self._ridge[i] for i in members],
                                                              [self.val[i] for i in members])
        return self._baselines

    def _groups(self) -> dict[str, list[int]]:
        """Indices of the validation sequences of subjects seen in training and of new ones, when both occur."""
        known = [i for i, s in enumerate(self.val) if s.subject in self.subjects]
        new = [i for i, s in enumerate(self.val) if s.subject not in self.subjects]
        return {"known_subjects": known, "new_subjects": new} if known and new else {}

    def evaluate(self, final: bool = False) -> dict[str, float]:
        """Validation metrics: ``rmse`` (streamed, UV units), the baselines, their ratio, and ``val_loss``
        (= ``rmse``; lower is better: what early stopping and best-checkpoint selection compare); with
        validation subjects both seen and unseen in training, each group's ``rmse_<group>`` and ridge too."""
        self.model.eval()
        predictions = self.predict(self.val)
        model_rmse = rmse(predictions, self.val)
        base = self.baselines()
        metrics = {"val_loss": model_rmse, "rmse": model_rmse, "ridge_rmse": base["ridge_rmse"],
                   "mean_rmse": base["mean_rmse"], "rmse_vs_ridge": model_rmse / base["ridge_rmse"]}
        for group, members in self._groups().items():
            metrics[f"rmse_{group}"] = rmse([predictions[i] for i in members], [self.val[i] for i in members])
            metrics[f"ridge_rmse_{group}"] = base[f"ridge_rmse_{group}"]
        if final:
            frames = sum(len(s) for s in self.val)
            print(f"\ntau RMSE on {len(self.val)} validation sequences ({frames} frames at {self.fps:g} fps), "
                  f"UV units:")
            ridge = f"ridge, {base['ridge_window_frames']:.0f}-frame window (lambda {base['ridge_lambda']:g})"
            for label, value in (("transformer (streamed)", model_rmse), (ridge, base["ridge_rmse"]),
                                 ("training mean", base["mean_rmse"])):
                print(f"  {label:<42}{value:.5f}")
            print(f"  transformer / ridge = {metrics['rmse_vs_ridge']:.3f}")
            for group, members in self._groups().items():
                print(f"  {group.replace('_', ' ')} ({len(members)} sequences): transformer "
                      f"{metrics[f'rmse_{group}']:.5f}, ridge {metrics[f'ridge_rmse_{group}']:.5f}, ratio "
                      f"{metrics[f'rmse_{group}'] / metrics[f'ridge_rmse_{group}']:.3f}")
        return metrics
