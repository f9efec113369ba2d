"""The training task of the expression -> larynx transformer: its model, batches, loss and evaluation.

Training: random crops of ``task.crop`` frames (starting anywhere, between frames too: psi and tau are
interpolated).  Besides AdamW's weight decay and dropout, a group lasso on the expression projection
(``task.input_sparsity``) shrinks the input weights of the expression channels tau does not follow: with a few
recordings many channels co-vary with tau by chance, and a new take moves them elsewhere.  The loss is the MSE of
normalised tau plus ``velocity_weight`` times the MSE of its frame differences.

Length of training: with ``trainer.max_steps`` null the task chooses it from the data
(:meth:`Task.steps_for_data`: ``task.epochs`` passes over the training frames, within
``[task.fewest_steps, task.most_steps]``); validation (``evaluate``) returns ``val_loss``, the streamed
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
    LarynxEnsemble,
    LarynxTransformerConfig,
    build_member,
    ensemble_of,
    transfer_weights,
)
from models.pretrained import default_checkpoint

from .baselines import fit_ridge, rmse, window_features
from .config import LarynxTaskConfig
from .data import LarynxData, crop_for, load_data


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
    try:
        build_member(source_config)  # a config of options this version does not have is refused
    except ValueError as e:
        raise InputError(f"task.init_from={init_from}: {path} does not fit this model: {e}") from None
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


def combine_members(checkpoints: list[dict], cfg: DictConfig) -> LarynxEnsemble:
    """The :class:`~models.larynx.LarynxEnsemble` of the members' weights (their subject tables joined;
    ``tasks.members``)."""
    members = []
    for state in checkpoints:
        member = build_member(state["model_config"])
        member.load_state_dict(state["model"])
        members.append(member)
    return ensemble_of(members)


def refits(cfg: DictConfig) -> bool:
    """Whether the members refit on all the data after their folds chose their lengths (``tasks.members``):
    ``task.refit`` on ``data=pairs`` (``data=synthetic`` validates on people of its own, not on training data)."""
    return bool(cfg.task.get("refit", False)) and cfg.data.kind == "pairs"


def evaluate_ensemble(cfg: DictConfig, ensemble, data: LarynxData) -> dict[str, float]:
    """The ensemble's own validation metrics where its members share one validation set (``data=synthetic``);
    ``{}`` on ``data=pairs``, where each member validates on another fold that the others trained on."""
    if not data.shared_validation:
        return {}
    settings: LarynxTaskConfig = to_dataclass(cfg.task, LarynxTaskConfig, where="task")
    train, val = training_indices(data, 0, settings, int(cfg.model.window), refit=False)[0], data.folds[0][1]
    ensemble.eval()
    with torch.no_grad():
        return evaluate(ensemble, [data.sequences[i] for i in val],
                        baselines(data, train, val, settings, float(cfg.data.fps)), settings.eval_batch, final=True)


def training_indices(data: LarynxData, member: int, settings: LarynxTaskConfig, window: int, refit: bool
                     ) -> tuple[list[int], int]:
    """(member ``member``'s training indices into ``data.sequences``, the crop): its fold's training sequences
    (and validation ones for a refit) of at least the crop (:func:`.data.crop_for`); the shorter are reported
    (printed) and not used."""
    train, val = data.folds[member]
    indices = train + val if refit else train
    crop = crop_for([data.sequences[i] for i in indices], int(settings.crop), window)
    short = [data.sequences[i] for i in indices if len(data.sequences[i]) < crop]
    if short:
        print(f"larynx_transformer: {len(short)} of {len(indices)} training sequences are shorter than the crop of "
              f"{crop} frames and are not used (lower task.crop to use them): "
              + ", ".join(f"{s.name} ({len(s)} frames)" for s in short))
    return [i for i in indices if len(data.sequences[i]) >= crop], crop


def baselines(data: LarynxData, train: list[int], val: list[int], settings: LarynxTaskConfig, fps: float
              ) -> dict[str, float]:
    """Validation RMSE of ridge regression on ``task.ridge_window`` seconds of psi and of the training mean, over
    all validation sequences and over those of known and of new subjects; computed once per training and
    validation set in a run (kept in ``data.baselines``)."""
    window = max(1, int(round(settings.ridge_window * fps)))
    key = (tuple(train), tuple(val), window, tuple(settings.ridge_lambdas))
    if key in data.baselines:
        return data.baselines[key]
    train_sequences, val_sequences = [data.sequences[i] for i in train], [data.sequences[i] for i in val]
    weights, lam = fit_ridge(train_sequences, window, list(settings.ridge_lambdas))
    ridge = [window_features(s.psi, window) @ weights for s in val_sequences]
    tau_mean = float(np.concatenate([s.tau for s in train_sequences]).astype(np.float64).mean())
    mean = [np.full(len(s), tau_mean) for s in val_sequences]
    out = {"ridge_rmse": rmse(ridge, val_sequences), "mean_rmse": rmse(mean, val_sequences), "ridge_lambda": lam,
           "ridge_window_frames": float(window)}
    subjects = {s.subject for s in train_sequences if s.subject is not None}
    for group, members in subject_groups(val_sequences, subjects).items():
        out[f"ridge_rmse_{group}"] = rmse([ridge[i] for i in members], [val_sequences[i] for i in members])
    data.baselines[key] = out
    return out


def subject_groups(val: list[LarynxSequence], subjects) -> dict[str, list[int]]:
    """Indices of the validation sequences of ``subjects`` (seen in training) and of others, when both occur."""
    known = [i for i, s in enumerate(val) if s.subject in subjects]
    new = [i for i, s in enumerate(val) if s.subject not in subjects]
    return {"known_subjects": known, "new_subjects": new} if known and new else {}


def predict(model, sequences: list[LarynxSequence], batch: int) -> list[np.ndarray]:
    """Autoregressive (streamed) tau of ``model`` for each sequence, ``batch`` at a time (shorter ones padded at
    the end); a sequence's subject's style when ``model`` knows them, else the average style."""
    out = []
    device = next(model.parameters()).device
    for first in range(0, len(sequences), batch):
        group = sequences[first:first + batch]
        length = max(len(s) for s in group)
        psi = np.stack([np.concatenate([s.psi, np.repeat(s.psi[-1:], length - len(s), 0)]) for s in group])
        subject = torch.tensor([model.subject_index(s.subject) if s.subject in model.subjects else 0 for s in group],
                               device=device)
        tau = model.generate(torch.from_numpy(psi).to(device), subject).cpu().numpy()
        out += [tau[i, :len(s)] for i, s in enumerate(group)]  # causal: padding cannot change these
    return out


def evaluate(model, val: list[LarynxSequence], base: dict[str, float], batch: int, final: bool = False
             ) -> dict[str, float]:
    """Validation metrics of ``model`` on ``val`` beside the baselines ``base`` (:func:`baselines`): ``rmse``
    (streamed, UV units), the baselines, their ratio, and ``val_loss`` (= ``rmse``; lower is better: what early
    stopping and best-checkpoint selection compare); with validation subjects both seen and unseen in training,
    each group's ``rmse_<group>`` and ridge too.  ``final``: printed as a table."""
    model.eval()
    predictions = predict(model, val, batch)
    model_rmse = rmse(predictions, val)
    metrics = {"val_loss": model_rmse, "rmse": model_rmse, "ridge_rmse": base["ridge_rmse"],
               "mean_rmse": base["mean_rmse"], "rmse_vs_ridge": model_rmse / base["ridge_rmse"]}
    groups = subject_groups(val, set(model.subjects))
    for group, members in groups.items():
        metrics[f"rmse_{group}"] = rmse([predictions[i] for i in members], [val[i] for i in members])
        metrics[f"ridge_rmse_{group}"] = base[f"ridge_rmse_{group}"]
    if final:
        frames = sum(len(s) for s in val)
        print(f"\ntau RMSE on {len(val)} validation sequences ({frames} frames at {model.fps:g} fps), UV units:")
        ridge = f"ridge, {base['ridge_window_frames']:.0f}-frame window (lambda {base['ridge_lambda']:g})"
        for label, value in (("transformer (streamed)", model_rmse), (ridge, base["ridge_rmse"]),
                             ("training mean", base["mean_rmse"])):
            print(f"  {label:<42}{value:.5f}")
        print(f"  transformer / ridge = {metrics['rmse_vs_ridge']:.3f}")
        for group, members in groups.items():
            print(f"  {group.replace('_', ' ')} ({len(members)} sequences): transformer "
                  f"{metrics[f'rmse_{group}']:.5f}, ridge {metrics[f'ridge_rmse_{group}']:.5f}, ratio "
                  f"{metrics[f'rmse_{group}'] / metrics[f'ridge_rmse_{group}']:.3f}")
    return metrics


class Task:
    """See the module docstring; the protocol is in ``tasks/__init__.py``."""

    def __init__(self, cfg: DictConfig, data: LarynxData | None = None):
        self.cfg = cfg
        self.settings: LarynxTaskConfig = to_dataclass(cfg.task, LarynxTaskConfig, where="task")
        sizes: LarynxTransformerConfig = to_dataclass(cfg.model, LarynxTransformerConfig, where="model")
        self.fps = float(cfg.data.fps)
        if self.settings.crop <= sizes.window:
            raise InputError(f"task.crop ({self.settings.crop}) must exceed model.window ({sizes.window}) so training "
                             f"sees full attention windows")
        self.member = int(self.settings.member or 0)  # which member of the ensemble this task trains
        refit = self.settings.refit_steps is not None  # a member's refit (tasks.members): its fold is training data
        if refit and cfg.data.kind != "pairs":
            raise InputError(f"task.refit_steps={self.settings.refit_steps}: a refit trains on the validation "
                             f"takes of data=pairs; data={cfg.data.kind} validates on data of its own")
        self.data = load_data(cfg) if data is None else data
        self.train_indices, crop = training_indices(self.data, self.member, self.settings, sizes.window, refit)
        self.val_indices = self.data.folds[self.member][1]
        self.crop = crop  # frames per training crop
        # the model, its normalisation and the baselines see these
        self.train = [self.data.sequences[i] for i in self.train_indices]
        self.val = [self.data.sequences[i] for i in self.val_indices]
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
        trainer_steps = cfg.trainer.get("max_steps") if "trainer" in cfg else None
        self.total_steps = int(trainer_steps) if trainer_steps else self.steps_for_data()

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

    def steps_for_data(self) -> int:
        """Training steps for these data: ``task.epochs`` passes over the training frames, within
        ``[task.fewest_steps, task.most_steps]`` (used when ``trainer.max_steps`` is null)."""
        s = self.settings
        frames = float(sum(len(sequence) for sequence in self.train))
        steps = s.epochs * frames / (s.batch_size * self.crop)
        return int(min(s.most_steps, max(s.fewest_steps, round(steps))))

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

    def baselines(self) -> dict[str, float]:
        """The validation RMSE of the ridge and training-mean baselines (:func:`baselines`)."""
        return baselines(self.data, self.train_indices, self.val_indices, self.settings, self.fps)

    def evaluate(self, final: bool = False) -> dict[str, float]:
        """The validation metrics of the model (:func:`evaluate`)."""
        return evaluate(self.model, self.val, self.baselines(), self.settings.eval_batch, final)
