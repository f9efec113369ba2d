"""Task: train the expression -> larynx transformer (``models.larynx_transformer``).

Data (``cfg.data.kind``):
- ``synthetic``: ``data.synthetic_larynx`` sequences; validation = held-out subjects (disjoint ids);
- ``pairs``: a folder of pair files (``data.pairs``), split into training and validation by file.
All sequences are resampled to one rate, ``cfg.data.fps`` (frames per second); tau is in UV units.

Training: random crops of ``task.crop`` frames.  Teacher forcing alone lets the model lean on the
true previous tau, which it never sees at inference, so it drifts; scheduled sampling replaces the
fed-back tau by the model's own predictions with a probability rising from 0 to
``scheduled_sampling.max_probability`` between the fractions ``start`` and ``end`` of training.
Predictions for all frames come from ``passes`` parallel no-grad passes (each pass feeds the
previous pass's predictions back; Duckworth et al., "Parallel Scheduled Sampling", 2019), and
the fed-back tau carries Gaussian noise of ``input_noise`` (in units of ``tau_scale``).
The loss is the MSE of normalised tau plus ``velocity_weight`` times the MSE of its frame differences.

Evaluation: autoregressive (streamed) tau RMSE on the validation sequences, beside two baselines
fitted on the training data: ridge regression on a causal window of ``ridge_window`` seconds of
psi (closed form, lambda chosen on a held-out part of the training subjects) and the training mean.
"""
from __future__ import annotations

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from data.errors import InputError

from data.splits import split_by_file
from data.pairs import LarynxSequence, load_pairs
from models.larynx_transformer import build_model  # also the task protocol's build_model(model_config)


# --------------------------------------------------------------------------- data


def load_sequences(data: DictConfig) -> tuple[list[LarynxSequence], list[LarynxSequence]]:
    """(training, validation) sequences for ``cfg.data``, at ``data.fps``."""
    if data.kind == "synthetic":
        from data.synthetic_larynx import make_dataset, split_subjects

        train_ids, heldout_ids = split_subjects(data.train_subjects, data.heldout_subjects)
        options = {"tau_noise": data.tau_noise, "swallows_per_minute": data.swallows_per_minute,
                   "blinks_per_minute": data.blinks_per_minute, "expression_noise": data.expression_noise}
        train = make_dataset(train_ids, data.sequences_per_subject, data.seconds, data.fps, data.seed, **options)
        val = make_dataset(heldout_ids, data.heldout_sequences_per_subject, data.seconds, data.fps, data.seed,
                           **options)
        return train, val
    if data.kind == "pairs":
        pairs = load_pairs(data.path, data.fps)
        return split_by_file(pairs, float(data.val_fraction), int(data.split_seed), f"pair file in {data.path}")
    raise ValueError(f"larynx_transformer: data.kind '{data.kind}' not supported (synthetic or pairs)")


def usable_sequences(train: list[LarynxSequence], crop: int) -> list[LarynxSequence]:
    """The training sequences of at least ``crop`` frames; the shorter ones are reported (printed) and
    dropped, and InputError if none is left."""
    usable = [s for s in train if len(s) >= crop]
    short = [s for s in train if len(s) < crop]
    if not usable:
        raise InputError(f"no training sequence has task.crop={crop} frames (longest: "
                         f"{max(len(s) for s in train)}); lower task.crop")
    if short:
        print(f"larynx_transformer: {len(short)} of {len(train)} training sequences are shorter than task.crop="
              f"{crop} frames and are not used: " + ", ".join(f"{s.name} ({len(s)} frames)" for s in short))
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


def fit_ridge(train: list[LarynxSequence], window: int, lambdas: list[float]) -> tuple[np.ndarray, float]:
    """Ridge weights [55*window+1] and the chosen lambda.

    lambda minimises the squared error on the last fifth of the training subjects (or sequences)
    when fitted on the rest; the weights are then refitted on everything.
    """
    subjects = sorted({s.subject for s in train}, key=str)
    if len(subjects) >= 2:
        held = set(subjects[-max(1, len(subjects) // 5):])
        fit_part = [s for s in train if s.subject not in held]
        check_part = [s for s in train if s.subject in held]
    else:
        cut = max(1, len(train) - max(1, len(train) // 5))
        fit_part, check_part = train[:cut], train[cut:]
    g_fit, c_fit, _, _ = _gram(fit_part, window)
    if check_part:
        g_chk, c_chk, yy_chk, _ = _gram(check_part, window)
        errors = []
        for lam in lambdas:
            w = _solve_ridge(g_fit, c_fit, lam)
            errors.append(w @ g_chk @ w - 2 * w @ c_chk + yy_chk)  # squared error on the check part
        best = float(lambdas[int(np.argmin(errors))])
        g_all, c_all = g_fit + g_chk, c_fit + c_chk
    else:
        best, g_all, c_all = float(lambdas[len(lambdas) // 2]), g_fit, c_fit
    return _solve_ridge(g_all, c_all, best), best


def rmse(predictions: list[np.ndarray], sequences: list[LarynxSequence]) -> float:
    """Root mean square tau error over all frames of all sequences (UV units)."""
    errors = np.concatenate([p - s.tau for p, s in zip(predictions, sequences)])
    return float(np.sqrt(np.mean(errors.astype(np.float64) ** 2)))


# --------------------------------------------------------------------------- task


class Task:
    """See the module docstring; the protocol is in ``tasks/__init__.py``."""

    def __init__(self, cfg: DictConfig):
        self.cfg = cfg
        self.settings = cfg.task
        self.fps = float(cfg.data.fps)
        crop = int(self.settings.crop)
        if crop <= cfg.model.window:
            raise ValueError(f"task.crop ({crop}) must exceed model.window ({cfg.model.window}) so training "
                             f"sees full attention windows")
        train, self.val = load_sequences(cfg.data)
        self.train = usable_sequences(train, crop)  # the model, its normalisation and the baselines see these
        self.subjects = sorted({s.subject for s in self.train if s.subject is not None})
        all_tau = np.concatenate([s.tau for s in self.train]).astype(np.float64)
        self.tau_mean = float(all_tau.mean())
        self._model_config = {
            **OmegaConf.to_container(cfg.model, resolve=True), "fps": self.fps, "subjects": self.subjects,
            "tau_mean": self.tau_mean, "tau_scale": float(max(all_tau.std(), 1e-6)),
        }
        self.model = build_model(self._model_config)

        # Training crops are gathered from one concatenated array.
        self.psi = torch.from_numpy(np.concatenate([s.psi for s in self.train]))
        self.tau = torch.from_numpy(np.concatenate([s.tau for s in self.train]))
        lengths = torch.tensor([len(s) for s in self.train])
        self.starts = torch.cat([torch.zeros(1, dtype=torch.long), lengths.cumsum(0)[:-1]])
        self.crop_counts = lengths - crop + 1  # valid crop positions per sequence
        self.seq_subject = torch.tensor([self.model.subject_index(s.subject) for s in self.train])
        self.seq_eta = torch.tensor([1.0 if s.eta is None else s.eta for s in self.train], dtype=torch.float32)
        self._baselines: dict[str, float] | None = None

    def model_config(self) -> dict:
        return self._model_config

    # ------------------------------------------------------------------ training

    def batch(self, step: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        """Random crops [B,crop] of training sequences, plus the random draws of the loss."""
        size, crop = int(self.settings.batch_size), int(self.settings.crop)
        sequence = torch.multinomial(self.crop_counts.double(), size, replacement=True, generator=generator)
        offset = (torch.rand(size, generator=generator, dtype=torch.float64) * self.crop_counts[sequence]).long()
        index = (self.starts[sequence] + offset)[:, None] + torch.arange(crop)
        subject = self.seq_subject[sequence]
        dropped = torch.rand(size, generator=generator) < self.settings.style_dropout
        return {
            "psi": self.psi[index], "tau": self.tau[index],
            "subject": torch.where(dropped, torch.zeros_like(subject), subject),
            "eta": self.seq_eta[sequence],
            "sample": torch.rand(size, crop, generator=generator),  # scheduled sampling draws
            "noise": torch.randn(size, crop, generator=generator),
        }

    def sampling_probability(self, step: int) -> float:
        """Probability of feeding back the model's own prediction at ``step`` (linear ramp)."""
        ss = self.settings.scheduled_sampling
        progress = step / max(1, self.cfg.trainer.max_steps)
        ramp = (progress - ss.start) / max(1e-9, ss.end - ss.start)
        return float(ss.max_probability * np.clip(ramp, 0.0, 1.0))

    def loss(self, batch: dict[str, torch.Tensor], step: int) -> tuple[torch.Tensor, dict[str, float]]:
        model = self.model
        psi, tau, subject = batch["psi"], batch["tau"], batch["subject"]
        eta = batch["eta"] if model.use_eta else None
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
        loss = mse + self.settings.velocity_weight * velocity
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
            subject = torch.tensor([self._style_index(s) for s in group])
            eta = torch.tensor([1.0 if s.eta is None else s.eta for s in group]) if self.model.use_eta else None
            tau = self.model.generate(torch.from_numpy(psi), subject, eta).numpy()
            out += [tau[i, :len(s)] for i, s in enumerate(group)]  # causal: padding cannot change these
        return out

    def _style_index(self, sequence: LarynxSequence) -> int:
        """Style of a validation sequence: its subject's if seen in training, else the average style."""
        return self.model.subject_index(sequence.subject) if sequence.subject in self.subjects else 0

    def baselines(self) -> dict[str, float]:
        """Validation RMSE of ridge regression on a window of psi and of the training mean (computed once)."""
        if self._baselines is None:
            window = max(1, int(round(self.settings.ridge_window * self.fps)))
            weights, lam = fit_ridge(self.train, window, list(self.settings.ridge_lambdas))
            ridge = [window_features(s.psi, window) @ weights for s in self.val]
            mean = [np.full(len(s), self.tau_mean) for s in self.val]
            self._baselines = {"ridge_rmse": rmse(ridge, self.val), "mean_rmse": rmse(mean, self.val),
                               "ridge_lambda": lam, "ridge_window_frames": float(window)}
        return self._baselines

    def evaluate(self, final: bool = False) -> dict[str, float]:
        self.model.eval()
        model_rmse = rmse(self.predict(self.val), self.val)
        base = self.baselines()
        metrics = {"rmse": model_rmse, "ridge_rmse": base["ridge_rmse"], "mean_rmse": base["mean_rmse"],
                   "rmse_vs_ridge": model_rmse / base["ridge_rmse"]}
        if final:
            frames = sum(len(s) for s in self.val)
            print(f"\ntau RMSE on {len(self.val)} validation sequences ({frames} frames at {self.fps:g} fps), UV units:")
            ridge = f"ridge, {base['ridge_window_frames']:.0f}-frame window (lambda {base['ridge_lambda']:g})"
            for label, value in (("transformer (streamed)", model_rmse), (ridge, base["ridge_rmse"]),
                                 ("training mean", base["mean_rmse"])):
                print(f"  {label:<42}{value:.5f}")
            print(f"  transformer / ridge = {metrics['rmse_vs_ridge']:.3f}")
        return metrics
