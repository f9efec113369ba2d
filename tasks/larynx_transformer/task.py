"""Task: train the expression -> larynx transformer (``models.larynx``).

Data (``cfg.data``, hydra group ``data``; every sequence is resampled to ``data.fps``; tau in UV units):
- ``data=synthetic`` (:class:`SyntheticData`): ``data.synthetic_larynx`` sequences.  Validation is
  on new recordings of the training subjects (with their style) and on held-out subjects drawn from
  a *shifted* generator (``data.heldout_shift``: lags, filters, gains, swallow shapes reaching outside
  the training ranges, with the average style), reported apart as well: a person's lag or gain
  cannot be seen in their face, so on new people every model, ridge included, is left with the
  average person's;
- ``data=pairs`` (:class:`PairsData`): a folder of pair files (``data.pairs``), split into training
  and validation **by take** (``data.pairs.take_of``: the files' ``take``, else the file name
  without a trailing clip number), so clips of one recording never sit on both sides.

Training: random crops of ``task.crop`` frames.  Besides AdamW's weight decay and dropout, a group lasso on the
expression projection (``task.input_sparsity``) shrinks the input weights of the expression channels tau does
not follow: with a few recordings many channels co-vary with tau by chance, and a new take moves them elsewhere.
``task.augment`` can alter crops in ways that keep psi and tau a pair: a time warp applied to both (a
rate per crop times a slow sinusoidal modulation), a gain and an offset per expression channel of psi,
whole channels dropped, white noise on every weight and frame.  All are off by default: on the real-regime
benchmark the first three made the held-out error larger (a warp changes the lags and time constants, which
are the person's, not the speech's; a gain on psi with tau kept teaches an invariance the larynx does not
have: its excursion follows the expression's amplitude); white noise of 0.03 lowered every family's mean
by 0.01-0.04 of ridge, less than one run moves with its training seed alone (benchmarks/README.md).
With ``model.feedback`` (FaceFormer's autoregression), teacher forcing alone lets the model lean on
the true previous tau, which it never sees at inference, so it drifts; scheduled sampling replaces
the fed-back tau by the model's own predictions with a probability rising from 0 to
``scheduled_sampling.max_probability`` between the fractions ``start`` and ``end`` of training.
Predictions for all frames come from ``passes`` parallel no-grad passes (each pass feeds the
previous pass's predictions back; Duckworth et al., "Parallel Scheduled Sampling", 2019), and the
fed-back tau carries Gaussian noise of ``input_noise`` (in units of ``tau_scale``).  The loss is the
MSE of normalised tau plus ``velocity_weight`` times the MSE of its frame differences.

Length of training: with ``trainer.max_steps`` null the task chooses it from the data
(:meth:`Task.max_steps`: ``task.epochs`` passes over the training frames, within
``[task.min_steps, task.max_steps]``); validation (``evaluate``) returns ``val_loss``, the streamed
validation RMSE, for early stopping and best-checkpoint selection.

Starting point: random weights, or with ``task.init_from`` another run's (``pretrained``: the shipped model,
trained on ``data=synthetic``; or a checkpoint path), all but the per-subject styles, which start at that
model's average person (:func:`warm_start`).  Off by default: on the real-regime benchmark it helped two
generator families of four and hurt one (benchmarks/README.md, "Expression -> larynx").

Evaluation: autoregressive (streamed) tau RMSE on the validation sequences, beside two baselines
fitted on the training data: ridge regression on a causal window of ``ridge_window`` seconds of
psi (closed form, lambda chosen by cross-validation over the training takes or subjects) and the
training mean.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from base.cli import REQUIRED, register_config, to_dataclass
from base.errors import InputError
from data.expressions import NUM_EXPRESSIONS
from data.pairs import LarynxSequence, load_pairs, split_by_take
from data.synthetic_larynx import (
    SWALLOW_CUES,
    TRAINING_RANGES,
    GeneratorRanges,
    heldout_ranges,
    make_dataset,
    make_sequence,
    split_subjects,
)
from models.checkpoint import load_checkpoint
from models.larynx import (
    SIZES,
    SIZES_BEFORE_OPTIONS,
    LarynxTransformerConfig,
    build_model,
    transfer_weights,
)
from models.pretrained import default_checkpoint

# --------------------------------------------------------------------------- configs


@dataclass
class ScheduledSampling:
    start: float = 0.1            # fraction of max_steps where the probability starts rising from 0
    end: float = 0.5              # ... and reaches max_probability
    max_probability: float = 1.0
    passes: int = 2               # parallel no-grad passes producing the fed-back predictions


@dataclass
class Augment:
    """Training-crop augmentation that keeps (psi, tau) a valid pair."""

    time_warp: float = 0.0        # crop rate drawn log-uniformly in [1/(1+w), 1+w] (psi and tau together)
    warp_wobble: float = 0.0      # amplitude of the slow sinusoidal modulation of that rate
    psi_gain: float = 0.0         # std of the log gain per expression channel of psi (clipped to [0, 1] after)
    psi_offset: float = 0.0       # std of an offset per expression channel of psi (a neutral pose of its own)
    channel_dropout: float = 0.0  # probability of zeroing an expression channel for a whole crop
    psi_noise: float = 0.0        # std of white noise on every expression weight and frame (tracker noise)


@dataclass
class LarynxTaskConfig:
    """``task=larynx_transformer``: crops, losses, augmentation, the length of training, the baselines."""

    name: str = "larynx_transformer"
    # Frames per training crop (must exceed model.window; the longest sequence's length when all are shorter).
    # The recurrent state runs from the crop's start, and at inference over whole takes: crops of 12.8 s
    # let it learn drives that build up over seconds (benchmarks/README.md, "Expression -> larynx").
    crop: int = 384
    batch_size: int = 16
    style_dropout: float = 0.25   # share of crops trained with the unknown-subject style (used for new subjects)
    input_noise: float = 0.1      # std of noise on the fed-back tau, in units of tau_scale
    velocity_weight: float = 0.5  # weight of the frame-difference MSE
    # Weight of a group lasso on the expression projection: the sum over expression channels of the norm of
    # each channel's input weights.  The larynx follows a few articulators; this shrinks the weights of the
    # others towards zero, so channels that only happen to co-vary with tau in few recordings, or that another
    # capture moves elsewhere, are not leant on (real-regime benchmark, seeds 0-3: better or equal on every
    # family, benchmarks/README.md).
    input_sparsity: float = 0.01
    scheduled_sampling: ScheduledSampling = field(default_factory=ScheduledSampling)
    augment: Augment = field(default_factory=Augment)
    # trainer.max_steps null: epochs passes over the training frames, within [min_steps, max_steps].
    epochs: float = 300.0
    min_steps: int = 600
    max_steps: int = 2000
    eval_batch: int = 32          # validation sequences decoded together
    ridge_window: float = 1.0     # seconds of psi the ridge baseline sees
    ridge_lambdas: list[float] = field(default_factory=lambda: [0.01, 0.1, 1.0, 10.0, 100.0, 1000.0, 1e4, 1e5])
    # Weights to start from instead of a random initialisation: a larynx_transformer checkpoint of the same
    # model sizes, or "pretrained" for the shipped model (trained on data=synthetic); see warm_start.
    init_from: str | None = None
    # Rehearsal: this share of each batch's training crops comes from data=synthetic's training people (its
    # defaults, each with a style of its own, named synthetic_<subject>), beside the pairs: the encoder keeps
    # seeing the generator's timing rules (a swallow needs a seal held with the jaw closed, and none comes
    # within the person's refractory time) that a few minutes of pairs show too seldom.  The length of
    # training, the tau normalisation, validation and the baselines follow the pairs alone.
    rehearsal: float = 0.0


@dataclass
class SyntheticData:
    """``data=synthetic``: talking faces and the larynx they drive (``data.synthetic_larynx``)."""

    kind: str = "synthetic"
    fps: float = 30.0
    seconds: float = 20.0                  # length of each sequence
    train_subjects: int = 24
    sequences_per_subject: int = 6
    new_takes_per_subject: int = 1         # validation: new recordings of the training subjects, and ...
    heldout_subjects: int = 6              # ... subjects never seen in training ...
    heldout_sequences_per_subject: int = 3
    heldout_shift: float = 1.0             # ... from a generator shifted this far (0: the training generator)
    seed: int = 0                          # data seed (independent of the training seed)
    tau_noise: float = 0.0005              # std of white tracker noise on tau (UV units; 0.03 ~ 1 cm)
    swallows_per_minute: float = 8.0       # swallows are placed in pauses of speech at about this rate
    blinks_per_minute: float = 15.0
    expression_noise: float = 0.01         # std of white tracker noise on each expression weight
    repeat_seals: float = 0.4              # share of swallows followed by a second seal (a swallow only
                                           # after the subject's refractory time)
    # What each person's swallows follow, drawn per person from these kinds (data.synthetic_larynx.SWALLOW_CUES:
    # seal, pause, snap, blink); every held-out person too.  One kind by default: with several, the model does
    # not learn whose swallows follow what (benchmarks/README.md, "Swallow cues").
    swallow_cues: list[str] = field(default_factory=lambda: ["seal"])


@dataclass
class PairsData:
    """``data=pairs``: a folder of pair files (``python -m data.pairs``), split by take."""

    kind: str = "pairs"
    path: str = REQUIRED
    fps: float = 30.0                      # every file is resampled to this rate
    val_fraction: float = 0.2              # share of takes held out for validation
    split_seed: int = 0


register_config("larynx_transformer_schema", LarynxTaskConfig, group="task")
register_config("larynx_transformer_synthetic_schema", SyntheticData, group="data_task")
register_config("larynx_transformer_pairs_schema", PairsData, group="data_task")
DATA_KINDS = {"synthetic": SyntheticData, "pairs": PairsData}


# --------------------------------------------------------------------------- data


def load_sequences(data) -> tuple[list[LarynxSequence], list[LarynxSequence]]:
    """(training, validation) sequences for ``cfg.data``, at ``data.fps``."""
    kind = data.kind if hasattr(data, "kind") else data["kind"]
    if kind not in DATA_KINDS:
        raise InputError(f"larynx_transformer: data.kind '{kind}' not supported ({' or '.join(DATA_KINDS)})")
    data = data if isinstance(data, DATA_KINDS[kind]) else to_dataclass(data, DATA_KINDS[kind], where="data")
    if kind == "synthetic":
        train_ids, heldout_ids = split_subjects(data.train_subjects, data.heldout_subjects)
        options = synthetic_options(data)
        train = synthetic_training_sequences(data, data.fps)
        frames = int(round(data.seconds * data.fps))
        new_takes = [make_sequence(subject, data.sequences_per_subject + i, frames, data.fps, data.seed, **options)
                     for subject in train_ids for i in range(data.new_takes_per_subject)]
        new_people = make_dataset(heldout_ids, data.heldout_sequences_per_subject, data.seconds, data.fps, data.seed,
                                  **{**options, "ranges": with_cues(heldout_ranges(data.heldout_shift), data)})
        return train, new_takes + new_people
    pairs = load_pairs(data.path, data.fps)
    return split_by_take(pairs, float(data.val_fraction), int(data.split_seed), f"take in {data.path}")


def with_cues(ranges: GeneratorRanges, data: SyntheticData) -> GeneratorRanges:
    """``ranges`` whose people swallow at the kinds of ``data.swallow_cues``; InputError naming an unknown kind."""
    cues = tuple(str(c) for c in data.swallow_cues)
    unknown = [c for c in cues if c not in SWALLOW_CUES]
    if unknown or not cues:
        raise InputError(f"data.swallow_cues: {', '.join(unknown) or 'empty'}; expected some of "
                         f"{', '.join(SWALLOW_CUES)}")
    return dataclasses.replace(ranges, cues=cues)


def synthetic_options(data: SyntheticData) -> dict:
    """The generator options of ``data`` (:func:`data.synthetic_larynx.make_sequence`'s keywords; the training
    people's ranges)."""
    return {"tau_noise": data.tau_noise, "swallows_per_minute": data.swallows_per_minute,
            "blinks_per_minute": data.blinks_per_minute, "expression_noise": data.expression_noise,
            "repeat_seals": data.repeat_seals, "ranges": with_cues(TRAINING_RANGES, data)}


def synthetic_training_sequences(data: SyntheticData, fps: float) -> list[LarynxSequence]:
    """The training people's sequences of ``data`` (``data=synthetic``), generated at ``fps``."""
    train_ids, _ = split_subjects(data.train_subjects, data.heldout_subjects)
    return make_dataset(train_ids, data.sequences_per_subject, data.seconds, fps, data.seed, **synthetic_options(data))


def rehearsal_sequences(fps: float) -> list[LarynxSequence]:
    """``data=synthetic``'s training sequences at its defaults (:class:`SyntheticData`), at ``fps``, each subject
    renamed ``synthetic_<subject>`` so that no name of the user's pairs is taken (``task.rehearsal``)."""
    return [dataclasses.replace(s, subject=f"synthetic_{s.subject}")
            for s in synthetic_training_sequences(SyntheticData(), fps)]


def crop_for(train: list[LarynxSequence], crop: int, window: int) -> int:
    """The training crop: ``task.crop`` frames, or the longest training sequence when all are shorter
    (printed); InputError when even that does not exceed ``model.window``."""
    longest = max(len(s) for s in train)
    if longest <= window:
        raise InputError(f"no training sequence is longer than model.window={window} frames (longest: {longest}); "
                         f"training needs crops of full attention windows: lower model.window")
    if longest < crop:
        print(f"larynx_transformer: every training sequence is shorter than task.crop={crop} frames: crops of "
              f"{longest} frames (the longest)")
    return min(crop, longest)


def usable_sequences(train: list[LarynxSequence], crop: int) -> list[LarynxSequence]:
    """The training sequences of at least ``crop`` frames; the shorter ones are reported (printed) and
    dropped (:func:`crop_for` leaves at least one)."""
    usable = [s for s in train if len(s) >= crop]
    short = [s for s in train if len(s) < crop]
    if short:
        print(f"larynx_transformer: {len(short)} of {len(train)} training sequences are shorter than the crop of "
              f"{crop} frames and are not used (lower task.crop to use them): "
              + ", ".join(f"{s.name} ({len(s)} frames)" for s in short))
    return usable


# --------------------------------------------------------------------------- baselines


def window_features(psi: np.ndarray, window: int) -> np.ndarray:
    """Causal window features [T, 55*window + 1]: psi[t-window+1..t] (first frame repeated before 0), then 1."""
    padded = np.concatenate([np.repeat(psi[:1], window - 1, axis=0), psi]).astype(np.float64)
    columns = [padded[k:k + len(psi)] for k in range(window)]
    return np.concatenate(columns + [np.ones((len(psi), 1))], axis=1)


def _gram(sequences: list[LarynxSequence], window: int) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Sums X^T X, X^T y, y^T y and the frame count over sequences."""
    gram, cross, yy, count = 0.0, 0.0, 0.0, 0
    for s in sequences:
        x, y = window_features(s.psi, window), s.tau.astype(np.float64)
        gram, cross, yy, count = gram + x.T @ x, cross + x.T @ y, yy + y @ y, count + len(y)
    return gram, cross, yy, count


def _solve_ridge(gram: np.ndarray, cross: np.ndarray, lam: float) -> np.ndarray:
    penalty = np.full(len(gram), lam)
    penalty[-1] = 0.0  # the intercept is not shrunk
    return np.linalg.solve(gram + np.diag(penalty), cross)


def ridge_groups(train: list[LarynxSequence]) -> list[str]:
    """What the ridge's lambda is cross-validated over, per sequence: its take where takes hold several
    sequences (clips of a recording, or several people's tau on one recording), else its subject, else the
    sequence itself."""
    takes, subjects = [s.take for s in train], [str(s.subject) for s in train]
    if len(set(takes)) < len(takes) and len(set(takes)) >= 2:
        return takes
    if len(set(subjects)) >= 2:
        return subjects
    return [s.name for s in train]


def fit_ridge(train: list[LarynxSequence], window: int, lambdas: list[float], folds: int = 5
              ) -> tuple[np.ndarray, float]:
    """Ridge weights [55*window+1] and the chosen lambda.

    lambda minimises the squared error of cross-validation over up to ``folds`` folds of the groups of
    :func:`ridge_groups` (takes, subjects or sequences: never frames of one recording on both sides); the
    weights are then refitted on everything.
    """
    groups = ridge_groups(train)
    names = sorted(set(groups))
    if len(names) < 2:
        gram, cross, _, _ = _gram(train, window)
        best = float(lambdas[len(lambdas) // 2])
        return _solve_ridge(gram, cross, best), best
    fold_of = {name: i % min(folds, len(names)) for i, name in enumerate(names)}
    parts = [_gram([s for s, g in zip(train, groups) if fold_of[g] == f], window)
             for f in range(min(folds, len(names)))]
    gram_all, cross_all = sum(p[0] for p in parts), sum(p[1] for p in parts)
    errors = np.zeros(len(lambdas))
    for gram, cross, yy, _ in parts:
        for j, lam in enumerate(lambdas):
            w = _solve_ridge(gram_all - gram, cross_all - cross, lam)
            errors[j] += w @ gram @ w - 2 * w @ cross + yy  # squared error on the held-out fold
    best = float(lambdas[int(np.argmin(errors))])
    return _solve_ridge(gram_all, cross_all, best), best


def rmse(predictions: list[np.ndarray], sequences: list[LarynxSequence]) -> float:
    """Root mean square tau error over all frames of all sequences (UV units)."""
    errors = np.concatenate([p - s.tau for p, s in zip(predictions, sequences)])
    return float(np.sqrt(np.mean(errors.astype(np.float64) ** 2)))


# --------------------------------------------------------------------------- warm start


def warm_start(model, init_from: str) -> None:
    """Start ``model`` from the weights of ``init_from`` (``task.init_from``): a checkpoint path, or
    ``pretrained`` for the shipped model.  The per-subject styles start from that model's average person
    (:func:`models.larynx.transfer_weights`).  InputError for a checkpoint of another task or
    of other model sizes; a note when it was trained at another frame rate (its filters are in frames)."""
    path = default_checkpoint("larynx_transformer") if init_from == "pretrained" else init_from
    try:
        state = load_checkpoint(path, "larynx_transformer")
    except InputError as e:
        raise InputError(f"task.init_from={init_from}: {e}") from None
    try:
        transfer_weights(model, state["model"])
    except ValueError as e:
        sizes = {**SIZES_BEFORE_OPTIONS, **state["model_config"]}
        differ = [f"model.{k}={sizes[k]}" for k in SIZES if k in sizes and sizes[k] != model.config[k]]
        hint = f"; it was trained with {', '.join(differ)}" if differ else ""
        raise InputError(f"task.init_from={init_from}: {path} does not fit this model: {e}{hint}") from None
    fps, source_fps = model.fps, float(state["model_config"].get("fps", model.fps))
    if source_fps != fps:
        print(f"larynx_transformer: task.init_from={init_from} was trained at {source_fps:g} fps, these data are "
              f"at {fps:g} fps: its filters, counted in frames, start at {source_fps / fps:.2f} times its durations")


# --------------------------------------------------------------------------- task


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
        share = float(self.settings.rehearsal)
        if not 0 <= share < 1:
            raise InputError(f"task.rehearsal must be in [0, 1), got {share}")
        train, self.val = load_sequences(cfg.data)
        self.crop = crop = crop_for(train, crop, sizes.window)  # frames per training crop
        self.train = usable_sequences(train, crop)  # the model, its normalisation and the baselines see these
        all_tau = np.concatenate([s.tau for s in self.train]).astype(np.float64)
        rehearsed = usable_sequences(rehearsal_sequences(self.fps), crop) if share > 0 else []
        sampled = self.train + rehearsed  # what the training crops are cut from
        self.subjects = sorted({s.subject for s in sampled if s.subject is not None})
        self.tau_mean = float(all_tau.mean())
        self._model_config = {
            **OmegaConf.to_container(OmegaConf.structured(sizes), resolve=True), "fps": self.fps,
            "subjects": self.subjects, "tau_mean": self.tau_mean, "tau_scale": float(max(all_tau.std(), 1e-6)),
        }
        self.model = build_model(self._model_config)
        if self.settings.init_from:
            warm_start(self.model, self.settings.init_from)

        # Training crops are gathered (and interpolated, see batch) from one concatenated array.
        self.psi = torch.from_numpy(np.concatenate([s.psi for s in sampled]))
        self.tau = torch.from_numpy(np.concatenate([s.tau for s in sampled]))
        lengths = torch.tensor([len(s) for s in sampled])
        self.starts = torch.cat([torch.zeros(1, dtype=torch.long), lengths.cumsum(0)[:-1]])
        self.lengths = lengths
        # How often each sequence is cropped: as often as it has crop positions (unwarped); with rehearsal, the
        # pairs' weights sum to 1 - share and the synthetic sequences' to share.
        self.crop_weights = (lengths - crop + 1).double()
        if rehearsed:
            pairs = len(self.train)
            self.crop_weights[:pairs] *= (1 - share) / self.crop_weights[:pairs].sum()
            self.crop_weights[pairs:] *= share / self.crop_weights[pairs:].sum()
        self.seq_subject = torch.tensor([self.model.subject_index(s.subject) for s in sampled])
        self.seq_eta = torch.tensor([1.0 if s.eta is None else s.eta for s in sampled], dtype=torch.float32)
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
        frames = float(sum(len(sequence) for sequence in self.train))  # the pairs (rehearsal adds none)
        steps = s.epochs * frames / (s.batch_size * self.crop)
        return int(min(s.max_steps, max(s.min_steps, round(steps))))

    # ------------------------------------------------------------------ training

    def _positions(self, size: int, generator: torch.Generator) -> tuple[torch.Tensor, torch.Tensor]:
        """Source positions [B,crop] (float, frames into the concatenated training arrays) of ``size`` crops,
        time-warped (``task.augment``), and each crop's sequence [B]."""
        crop, augment = self.crop, self.settings.augment
        sequence = torch.multinomial(self.crop_weights, size, replacement=True, generator=generator)
        uniform = torch.rand(size, 1, generator=generator, dtype=torch.float64)
        log_rate = math.log1p(augment.time_warp) * (2 * uniform - 1)
        cycles = crop / (torch.rand(size, 1, generator=generator, dtype=torch.float64) * 60 + 40)  # 40-100 frame period
        phase = 2 * math.pi * torch.rand(size, 1, generator=generator, dtype=torch.float64)
        frame = torch.arange(crop - 1, dtype=torch.float64)[None]
        rate = torch.exp(log_rate) * (1 + augment.warp_wobble * torch.sin(2 * math.pi * cycles * frame / crop + phase))
        offsets = torch.cat([torch.zeros(size, 1, dtype=torch.float64), rate.cumsum(1)], dim=1)  # [B,crop]
        last = (self.lengths[sequence] - 1).double()
        offsets = offsets * torch.clamp(last / offsets[:, -1], max=1.0)[:, None]  # slower where a sequence is short
        start = torch.rand(size, generator=generator, dtype=torch.float64) * (last - offsets[:, -1])
        return self.starts[sequence].double()[:, None] + start[:, None] + offsets, sequence

    def batch(self, step: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Random crops [B,crop] of training sequences, augmented, plus the random draws of the loss."""
        size, crop = int(self.settings.batch_size), self.crop
        positions, sequence = self._positions(size, generator)
        low = positions.floor().long()
        high = torch.minimum(low + 1, (self.starts[sequence] + self.lengths[sequence] - 1)[:, None])
        frac = (positions - low.double()).float()
        psi = torch.lerp(self.psi[low], self.psi[high], frac[..., None])
        tau = torch.lerp(self.tau[low], self.tau[high], frac)
        augment = self.settings.augment
        gain = torch.exp(augment.psi_gain * torch.randn(size, 1, psi.shape[2], generator=generator))
        offset = augment.psi_offset * torch.randn(size, 1, psi.shape[2], generator=generator)
        kept = torch.rand(size, 1, psi.shape[2], generator=generator) >= augment.channel_dropout
        psi = psi * gain + offset
        if augment.psi_noise:  # drawn only when asked for: the default runs' random streams stay as they were
            psi = psi + augment.psi_noise * torch.randn(psi.shape, generator=generator)
        psi = psi.clamp(0.0, 1.0) * kept
        subject = self.seq_subject[sequence]
        dropped = torch.rand(size, generator=generator) < self.settings.style_dropout
        return {
            "psi": psi, "tau": tau,
            "subject": torch.where(dropped, torch.zeros_like(subject), subject),
            "eta": self.seq_eta[sequence],
            "sample": torch.rand(size, crop, generator=generator),  # scheduled sampling draws
            "noise": torch.randn(size, crop, generator=generator),
        }

    def sampling_probability(self, step: int) -> float:
        """Probability of feeding back the model's own prediction at ``step`` (linear ramp)."""
        ss = self.settings.scheduled_sampling
        progress = step / max(1, self.total_steps)
        ramp = (progress - ss.start) / max(1e-9, ss.end - ss.start)
        return float(ss.max_probability * np.clip(ramp, 0.0, 1.0))

    def loss(self, batch: dict[str, torch.Tensor], step: int) -> tuple[torch.Tensor, dict[str, float]]:
        model = self.model
        psi, tau, subject = batch["psi"], batch["tau"], batch["subject"]
        eta = batch["eta"] if model.use_eta else None
        sparsity = self.settings.input_sparsity * model.expression.project.weight.view(
            model.expression.project.out_features, NUM_EXPRESSIONS, -1).norm(dim=(0, 2)).sum()
        if not model.feedback:  # nothing fed back: no teacher forcing, nothing to sample
            error = (model(psi, None, subject, eta) - tau) / model.tau_scale
            mse = error.pow(2).mean()
            loss = mse + self.settings.velocity_weight * (error[:, 1:] - error[:, :-1]).pow(2).mean() + sparsity
            return loss, {"loss": loss.item(), "mse": mse.item()}
        teacher = model.shift(tau)
        previous = teacher
        probability = self.sampling_probability(step)
        if probability > 0:
            own = batch["sample"] < probability
            with torch.no_grad():
                for _ in range(int(self.settings.scheduled_sampling.passes)):
                    predicted = model(psi, previous, subject, eta)
                    previous = torch.where(own, model.shift(predicted), teacher)
        previous = previous + self.settings.input_noise * model.tau_scale * batch["noise"]
        error = (model(psi, previous, subject, eta) - tau) / model.tau_scale
        mse = error.pow(2).mean()
        velocity = (error[:, 1:] - error[:, :-1]).pow(2).mean()
        loss = mse + self.settings.velocity_weight * velocity + sparsity
        return loss, {"loss": loss.item(), "mse": mse.item(), "sampling": probability}

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
            eta = (torch.tensor([1.0 if s.eta is None else s.eta for s in group], device=self.device)
                   if self.model.use_eta else None)
            tau = self.model.generate(torch.from_numpy(psi).to(self.device), subject, eta).cpu().numpy()
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
