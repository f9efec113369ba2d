"""Training task: head orientation -> the 8 cervical joint rotations (``python train.py task=head2neck``).

Config groups (structured: the dataclasses below and ``models.head2neck.Head2NeckConfig`` are the schemas
and the defaults; the YAML files hold only what differs):
- ``task``: :class:`Head2NeckTaskConfig` (``configs/task/head2neck.yaml``);
- ``model``: ``models.head2neck.Head2NeckConfig`` (``configs/model/head2neck.yaml``);
- ``data`` (``configs/data_task/head2neck_<data>.yaml``):
  - ``data=synthetic`` (default), :class:`SyntheticData`: sequences of the in-vivo prior
    (``data.cervical_prior``, its settings under ``data.prior``), one person each; validation sequences
    come from another seed (``val_seed`` != ``seed``), so from new persons;
  - ``data=theta_seq data.path=...``, :class:`ThetaSeqData`: the user's own theta sequences (a ``.npy``
    ``[T,8,3]``, HACK release layout: bone frames of ``rig``; per frame, so no frame rate; or the
    ``params.npz`` of a fit, ``motion.fit``, whose rig checksum must be ``rig``'s; or a folder of either,
    e.g. a folder of fit folders).  Several files are split by file (``val_fraction`` of them, chosen with
    ``split_seed``), a single file by time (its last ``val_fraction`` of frames); validation is on the
    held-out frames of the files only.  By default (``data.calibrate=true``) the training frames decide how
    far to trust them (``tasks.head2neck_calibration``: time-blocked cross-validation over the starting point,
    the prior's share and style and the length, the shipped preset kept when nothing beats it); the chosen
    model is trained there and the loop only evaluates and saves it (``trainer.max_steps`` stays null;
    ``data.start``, ``data.prior_weight``, ``data.steps`` fix a choice).  ``data.calibrate=false``: the loop
    trains ``trainer.max_steps`` (null: 2000) steps from ``data.start`` (scratch by default) with
    ``data.prior_weight`` (0 by default: the files alone) of every batch drawn from the prior.
Head orientations are the rig's forward kinematics of the poses (``cfg.rig``, built-in by default).
Poses are handled in the joints' anatomical frames (``HeadNeckModel.to_anatomical``), where the limits and
the prior are written; real sequences arrive in bone frames and are converted.  The trained model holds
nothing of the rig (``models.head2neck``): it reads the rig's rest frames when it runs.

Loss per batch of frames::

    mean_j |R_j - R_j*|^2 / 2  +  lambda_fk |H(theta) - H*|^2 / 2  +  lambda_rot E_rot  +  lambda_sim E_sim

(``|R - R*|^2 / 2 = 2 (1 - cos angle)``, about angle^2 in radians^2; E_rot and E_sim from
``data.joint_limits``).  Evaluation: per-joint angular error (degrees) of the model after the exact
correction, of the model's raw output (with its own head error and share of joints inside the limits: the
correction makes those hold for any output, so they are what shows the network learnt), and of the two
analytic baselines after the same correction.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from omegaconf import DictConfig

from base.cli import REQUIRED, register_config, to_dataclass
from base.errors import InputError
from base.rotations import axis_angle_to_matrix, relative_angle
from data.cervical_prior import PriorConfig, head_rotations, load_theta_sequences, sample_sequences
from data.joint_limits import within_limits
from data.splits import split_by_file
from models.head2neck import (
    Head2NeckConfig,
    Head2NeckMLP,
    build_model,
    correct_to_head,
    head_error_deg,
    model_config,
    split_head_rotation,
)
from models.rig import HeadNeckModel
from tasks.head2neck_calibration import STARTS, CalibrationConfig, better_preset, calibrate, load_preset
from tasks.head2neck_stack import pose_loss

__all__ = ["Task", "build_model", "Head2NeckTaskConfig", "SyntheticData", "ThetaSeqData"]


@dataclass
class Head2NeckTaskConfig:
    """The loss and batches of the head2neck task."""

    name: str = "head2neck"
    batch_size: int = 1024           # frames per step, drawn from the training sequences
    lambda_fk: float = 1.0           # head orientation consistency
    lambda_rot: float = 1.0          # E_rot, the limits
    lambda_sim: float = 1.0e-4       # E_sim pulls neighbours together, against the truth (C1-C2 vs O-C1): keep it small
    correction_iterations: int = 3   # at most this many Gauss-Newton steps of the exact correction

    def __post_init__(self) -> None:
        if self.batch_size < 1 or self.correction_iterations < 0:
            raise ValueError(f"batch_size={self.batch_size}, correction_iterations={self.correction_iterations}: "
                             f"expected a batch of at least 1 frame and a non-negative number of steps")
        for name in ("lambda_fk", "lambda_rot", "lambda_sim"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"{name}={getattr(self, name)}: expected a non-negative weight")


@dataclass
class SyntheticData:
    """``data=synthetic``: the in-vivo prior (``data.cervical_prior``)."""

    kind: str = "synthetic"
    train_sequences: int = 1024      # one new person each
    val_sequences: int = 128
    seed: int = 1
    val_seed: int = 2                # validation persons: another seed
    prior: PriorConfig = field(default_factory=PriorConfig)

    def __post_init__(self) -> None:
        for name in ("train_sequences", "val_sequences"):
            if int(getattr(self, name)) < 1:
                raise ValueError(f"{name} is {getattr(self, name)}, expected at least 1")
        if self.val_seed == self.seed:
            raise ValueError(f"val_seed equals seed ({self.seed}): the validation persons would be the training "
                             f"persons; choose another val_seed")


@dataclass
class ThetaSeqData:
    """``data=theta_seq``: real theta sequences, alone or mixed with the prior."""

    kind: str = "theta_seq"
    # a .npy [T,8,3] (bone frames, axis-angle radians), a fit's params.npz (motion.fit; checked against rig=),
    # or a folder of them (e.g. a folder of fit folders)
    path: str = REQUIRED
    val_fraction: float = 0.2        # files held out (several files) or last frames held out (one file)
    split_seed: int = 0              # which files are held out
    calibrate: bool = True           # cross-validate on time blocks how far to trust the files (module docstring)
    start: str | None = None         # default | hack | preset (the better) | scratch; null: chosen, or scratch
    prior_weight: float | None = None  # share of each batch drawn from the prior; null: chosen (calibrate) or 0
    steps: int | None = None         # training length when calibrating; null: chosen
    prior_sequences: int = 1024      # prior sequences to draw batches from when prior_weight > 0 (calibrate=false)
    prior_seed: int = 1
    prior: PriorConfig = field(default_factory=PriorConfig)   # calibrate=true: the style follows the preset
    calibration: CalibrationConfig = field(default_factory=CalibrationConfig)

    def __post_init__(self) -> None:
        if self.prior_weight is not None and not 0 <= float(self.prior_weight) < 1:
            raise ValueError(f"prior_weight={self.prior_weight}: expected a share in [0, 1) (1 would ignore the "
                             f"files; use data=synthetic)")
        if int(self.prior_sequences) < 1:
            raise ValueError(f"prior_sequences is {self.prior_sequences}, expected at least 1")
        if self.start is not None and self.start not in STARTS:
            raise ValueError(f"start={self.start}: expected one of {', '.join(STARTS)} (or null)")
        if self.steps is not None and int(self.steps) < 0:
            raise ValueError(f"steps={self.steps}: expected a non-negative length (or null)")


register_config("head2neck_task_schema", Head2NeckTaskConfig, group="task")
register_config("head2neck_model_schema", Head2NeckConfig, group="model")
register_config("head2neck_synthetic_schema", SyntheticData, group="data_task")
register_config("head2neck_theta_seq_schema", ThetaSeqData, group="data_task")

DEFAULT_STEPS = 2000   # the loop's length when trainer.max_steps is null and nothing is calibrated
DATA_FILES = {"synthetic": "configs/data_task/head2neck_synthetic.yaml",
              "theta_seq": "configs/data_task/head2neck_theta_seq.yaml"}


def data_config(data: DictConfig) -> SyntheticData | ThetaSeqData:
    """The ``data`` section as its dataclass; InputError naming the section for a bad value."""
    kind = data.get("kind")
    if kind not in DATA_FILES:
        raise InputError(f"data.kind={kind}: task head2neck trains on data=synthetic or data=theta_seq")
    cls = SyntheticData if kind == "synthetic" else ThetaSeqData
    return to_dataclass(data, cls, where=f"data ({DATA_FILES[kind]})")


def split_sequences(sequences: list[np.ndarray], val_fraction: float, seed: int, path: str
                    ) -> tuple[list[np.ndarray], list[np.ndarray], str]:
    """(train, val, description): by file when there are several (``data.splits.split_by_file``), else the
    last ``val_fraction`` of the one file's frames."""
    if len(sequences) == 1:
        if not 0 < val_fraction < 1:
            raise InputError(f"{path}: val_fraction must be in (0, 1), got {val_fraction}")
        theta = sequences[0]
        cut = int(round(len(theta) * (1 - val_fraction)))
        if cut < 1 or cut >= len(theta):
            raise InputError(f"{path}: {len(theta)} frames are too few to hold out {val_fraction:.0%} of them")
        return [theta[:cut]], [theta[cut:]], f"the last {len(theta) - cut} frames of {path}"
    train, val = split_by_file(sequences, val_fraction, seed, f"theta sequence in {path}")
    return train, val, f"{len(val)} of the {len(sequences)} sequences in {path}"


def prior_frames(count: int, seed: int, config: PriorConfig) -> np.ndarray:
    """Anatomical theta [count * T, J, 3] of ``count`` prior sequences."""
    sequences = sample_sequences(count, seed, config)
    return sequences.theta.reshape(-1, *sequences.theta.shape[2:])


class Task:
    def __init__(self, cfg: DictConfig):
        self.cfg = cfg
        self.task = to_dataclass(cfg.task, Head2NeckTaskConfig, where="task (configs/task/head2neck.yaml)")
        self.data = data_config(cfg.data)
        self.rig = HeadNeckModel.from_config(cfg.rig)
        self.model = Head2NeckMLP(to_dataclass(cfg.model, Head2NeckConfig,
                                               where="model (configs/model/head2neck.yaml)"))
        self.rest = self.rig.anatomical_rest_rotations
        train, val, self.val_description = self._sequences()
        self.train = self._frames(np.concatenate(train))
        self.val = self._frames(np.concatenate(val))
        self.prior, self.prior_weight, self.calibration = None, 0.0, None
        self.total_steps = DEFAULT_STEPS   # trainer.max_steps=null (configs/trainer/head2neck.yaml)
        if isinstance(self.data, ThetaSeqData):
            if self.data.calibrate:
                self._calibrate(train, cfg)
            else:
                self._fixed_knobs(train)
        self._baselines: dict | None = None

    # ------------------------------------------------------------------ calibration (data=theta_seq)

    def _calibrate(self, train: list[np.ndarray], cfg: DictConfig) -> None:
        """Choose and train the model by time-blocked cross-validation (``tasks.head2neck_calibration``); the
        loop then trains no step."""
        max_steps = cfg.trainer.get("max_steps")
        if max_steps is not None:
            raise InputError(f"trainer.max_steps={max_steps} with data.calibrate=true: the calibration trains the "
                             f"model itself and chooses its length (fix it with data.steps={max_steps}), or set "
                             f"data.calibrate=false to train {max_steps} steps in the loop")
        data, task = self.data, self.task
        self.calibration = calibrate(
            [torch.as_tensor(t, dtype=torch.float32) for t in train], self.rig, self.model.config,
            {"lambda_fk": float(task.lambda_fk), "lambda_rot": float(task.lambda_rot),
             "lambda_sim": float(task.lambda_sim)}, data.calibration, data.prior, data.start,
            None if data.prior_weight is None else float(data.prior_weight),
            None if data.steps is None else int(data.steps))
        self.model = self.calibration.model
        self.total_steps = 0

    def _fixed_knobs(self, train: list[np.ndarray]) -> None:
        """``data.calibrate=false``: the loop trains from ``data.start`` with ``data.prior_weight`` of the prior."""
        data = self.data
        start = data.start or "scratch"
        if start == "preset":
            start = better_preset(torch.as_tensor(np.concatenate(train), dtype=torch.float32), self.rig)
        if start != "scratch":
            self.model = load_preset(start)
        self.prior_weight = float(data.prior_weight or 0.0)
        if self.prior_weight > 0:
            self.prior = self._frames(prior_frames(data.prior_sequences, data.prior_seed, data.prior))
        if data.steps is not None:
            self.total_steps = int(data.steps)

    # ------------------------------------------------------------------ data

    def _sequences(self) -> tuple[list[np.ndarray], list[np.ndarray], str]:
        data = self.data
        if isinstance(data, SyntheticData):
            train = prior_frames(data.train_sequences, data.seed, data.prior)
            val = prior_frames(data.val_sequences, data.val_seed, data.prior)
            description = (f"{data.val_sequences} synthetic sequences of new persons (seed {data.val_seed}, "
                           f"{data.prior.seconds:g} s at {data.prior.fps:g} fps)")
            return [train], [val], description
        sequences = [self.rig.to_anatomical(torch.as_tensor(s.theta)).numpy()  # release layout: bone frames
                     for s in load_theta_sequences(data.path, self.rig.num_joints, self.rig.rig)]
        return split_sequences(sequences, float(data.val_fraction), int(data.split_seed), str(data.path))

    def _frames(self, theta: np.ndarray) -> dict[str, torch.Tensor]:
        theta = torch.as_tensor(theta, dtype=torch.float32)
        return {"rotations": axis_angle_to_matrix(theta), "head": head_rotations(self.rig, theta)}

    def batch(self, step: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        size = int(self.task.batch_size)
        from_prior = 0 if self.prior is None else int(round(size * self.prior_weight))
        index = torch.randint(len(self.train["head"]), (size - from_prior,), generator=generator)
        batch = {name: value[index] for name, value in self.train.items()}
        if from_prior:
            index = torch.randint(len(self.prior["head"]), (from_prior,), generator=generator)
            batch = {name: torch.cat([value, self.prior[name][index]]) for name, value in batch.items()}
        return batch

    # ------------------------------------------------------------------ loss

    def loss(self, batch: dict[str, torch.Tensor], step: int) -> tuple[torch.Tensor, dict[str, float]]:
        task = self.task
        return pose_loss(self.model(batch["head"], self.rest), batch["rotations"], batch["head"], self.rig,
                         task.lambda_fk, task.lambda_rot, task.lambda_sim)

    # ------------------------------------------------------------------ evaluation

    @torch.no_grad()
    def evaluate(self, final: bool = False) -> dict[str, float]:
        head = self.val["head"]
        iterations = int(self.task.correction_iterations)
        raw = torch.cat([self.model(h, self.rest) for h in head.split(8192)])
        rows = {"model": self._row(correct_to_head(raw, head, self.rig, iterations)), "model_raw": self._row(raw),
                **self._baseline_rows()}
        per_joint, head_mean, head_max, inside = rows["model"]
        metrics = {"joint_err_deg": float(per_joint.mean()), "head_err_max_deg": head_max, "within_limits": inside}
        metrics.update({f"joint_err_deg_{n}": float(e) for n, e in zip(self.rig.joint_names, per_joint)})
        for name in ("model_raw", "uniform", "rom", "invivo"):
            per_joint, head_mean, head_max, inside = rows[name]
            metrics.update({f"{name}_joint_err_deg": float(per_joint.mean()), f"{name}_head_err_mean_deg": head_mean,
                            f"{name}_head_err_max_deg": head_max, f"{name}_within_limits": inside})
        if self.calibration is not None:
            choice = self.calibration
            metrics.update(calibration_heldout_err_deg=choice.error,
                           calibration_preset_heldout_err_deg=choice.preset_error,
                           calibration_kept_preset=float(choice.candidate is None),
                           calibration_steps=float(choice.steps),
                           calibration_prior_weight=choice.candidate.prior_weight if choice.candidate else 0.0)
        if final:
            self._print_table(rows, len(head))
        return metrics

    def _row(self, theta: torch.Tensor) -> tuple[torch.Tensor, float, float, float]:
        """(per-joint angular error [J] degrees, mean and max head error degrees, share within limits) on val."""
        head, truth = self.val["head"], self.val["rotations"]
        per_joint = torch.rad2deg(relative_angle(axis_angle_to_matrix(theta), truth)).mean(0)
        error = head_error_deg(theta, head, self.rig)
        return per_joint, float(error.mean()), float(error.max()), float(within_limits(theta).float().mean())

    def _baseline_rows(self) -> dict[str, tuple]:
        """The uniform, ROM and in-vivo splits (with the same correction) on val: computed once, they do not learn."""
        if self._baselines is None:
            head = self.val["head"]
            iterations = int(self.task.correction_iterations)
            self._baselines = {split: self._row(correct_to_head(split_head_rotation(head, self.rest, split), head,
                                                                self.rig, iterations))
                               for split in ("uniform", "rom", "invivo")}
        return self._baselines

    def _print_table(self, rows: dict, frames: int) -> None:
        labels = {"model": "MLP + correction", "model_raw": "MLP (raw output)",
                  "uniform": "uniform split + correction", "rom": "ROM split + correction",
                  "invivo": "in-vivo split + correction"}
        names = self.rig.joint_names
        print(f"\nhead2neck: per-joint angular error (deg) on {frames} held-out frames ({self.val_description})")
        print(f"{'method':27s}{'mean':>7s}" + "".join(f"{n:>7s}" for n in names)
              + f"{'head mean':>10s}{'head max':>10s}{'in limits':>11s}")
        for key, label in labels.items():
            per_joint, head_mean, head_max, inside = rows[key]
            print(f"{label:27s}{float(per_joint.mean()):7.2f}" + "".join(f"{float(e):7.2f}" for e in per_joint)
                  + f"{head_mean:10.1e}{head_max:10.1e}{inside:11.4f}")

    def model_config(self) -> dict:
        return model_config(self.model)

    def to(self, device: torch.device) -> Task:
        """Move the model, the rig, its rest rotations and the validation frames to ``device``
        (tasks/__init__.py).  The training frames stay on the CPU: ``batch`` draws from them with a CPU
        generator and train.py moves each batch."""
        self.model.to(device)
        self.rig.to(device)
        self.rest = self.rest.to(device)
        self.val = {name: value.to(device) for name, value in self.val.items()}
        self._baselines = None
        return self
