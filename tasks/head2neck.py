"""Training task: head orientation -> the 8 cervical joint rotations (``python train.py task=head2neck``).

Data (``cfg.data.kind``):
- ``synthetic`` (default): sequences of the anatomical prior (``data.cervical_prior``), one person
  each; validation sequences come from another seed (``val_seed`` != ``seed``), so from new persons.
  Every key of ``data`` is a PriorConfig field or one of ``SYNTHETIC_KEYS`` (else InputError).
- ``theta_seq``: real theta sequences (``data.path``: a ``.npy`` ``[T,8,3]`` or a folder of them; the
  mapping is per frame, so no frame rate); several files are split by file (``val_fraction`` of them,
  chosen with ``split_seed``), a single file by time (its last ``val_fraction`` of frames).
Head orientations are the rig's forward kinematics of the poses (``cfg.rig``, built-in by default).
Poses are handled in the joints' anatomical frames (``HeadNeckModel.to_anatomical``), where the limits
and the prior are written; real sequences arrive in bone frames (the release's layout) and are converted.

Loss per batch of frames (``configs/task/head2neck.yaml``)::

    mean_j |R_j - R_j*|^2 / 2  +  lambda_fk |H(theta) - H*|^2 / 2  +  lambda_rot E_rot  +  lambda_sim E_sim

(``|R - R*|^2 / 2 = 2 (1 - cos angle)``, about angle^2 in radians^2; E_rot and E_sim from
``models.joint_limits``).  Evaluation: per-joint angular error (degrees) of the model after the exact
correction, of the model's raw output, and of the two analytic baselines after the same correction,
the head orientation error and the share of joints inside the limits.  The ROM split does not
reproduce the head by itself; the uniform split does, but on the default prior it puts ~15% of the
joints (in half the frames; built-in and real rig alike) outside their limits, which the correction
clamps and redistributes.
"""
from __future__ import annotations

import math

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

from data.cervical_prior import PriorConfig, head_rotations, load_theta_sequences, sample_sequences
from data.cli import config_dataclass
from data.errors import InputError
from data.splits import split_by_file
from models.head2neck import build_model, chain_head_rotation, correct_to_head, head_error_deg, split_head_rotation
from models.joint_limits import adjacent_similarity_energy, rotation_limit_energy, within_limits
from models.rig import HeadNeckModel
from models.rotations import axis_angle_to_matrix, relative_angle

__all__ = ["Task", "build_model"]


# The synthetic data section's own keys (configs/data/synthetic.yaml, configs/data_task/head2neck_synthetic.yaml);
# its other keys are the generator's, the fields of PriorConfig.
SYNTHETIC_KEYS = ("kind", "seed", "val_seed", "train_sequences", "val_sequences")


def prior_config(data: DictConfig) -> PriorConfig:
    """The generator settings of the synthetic ``cfg.data``; InputError for an unknown key, fewer than one
    training or validation sequence, or ``val_seed == seed`` (the validation persons would be the
    training persons)."""
    where = "data (configs/data_task/head2neck_synthetic.yaml)"
    values = OmegaConf.to_container(data, resolve=True)
    for key in ("train_sequences", "val_sequences"):
        if not int(values[key]) >= 1:
            raise InputError(f"{where}: {key} is {values[key]}, expected at least 1")
    if values["val_seed"] == values["seed"]:
        raise InputError(f"{where}: val_seed equals seed ({values['seed']}): the validation persons would be the "
                         f"training persons; choose another val_seed")
    return config_dataclass(PriorConfig, values, where, other_keys=SYNTHETIC_KEYS)


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


class Task:
    def __init__(self, cfg: DictConfig):
        self.cfg = cfg
        self.rig = HeadNeckModel.from_config(cfg.rig)
        self._model_config = {**OmegaConf.to_container(cfg.model, resolve=True),
                              "rest_rotations": self.rig.anatomical_rest_rotations.tolist()}
        self.model = build_model(self._model_config)
        train, val, self.val_description = self._sequences(cfg.data)
        self.train = self._frames(np.concatenate(train))
        self.val = self._frames(np.concatenate(val))
        self._baselines: dict | None = None

    # ------------------------------------------------------------------ data

    def _sequences(self, data: DictConfig) -> tuple[list[np.ndarray], list[np.ndarray], str]:
        if data.kind == "synthetic":
            config = prior_config(data)
            train = sample_sequences(int(data.train_sequences), int(data.seed), config)
            val = sample_sequences(int(data.val_sequences), int(data.val_seed), config)
            description = (f"{data.val_sequences} synthetic sequences of new persons (seed {data.val_seed}, "
                           f"{config.seconds:g} s at {config.fps:g} fps)")
            return [train.theta.reshape(-1, *train.theta.shape[2:])], \
                [val.theta.reshape(-1, *val.theta.shape[2:])], description
        if data.kind == "theta_seq":
            sequences = [self.rig.to_anatomical(torch.as_tensor(s.theta)).numpy()  # release layout: bone frames
                         for s in load_theta_sequences(data.path, self.rig.num_joints)]
            return split_sequences(sequences, float(data.val_fraction), int(data.split_seed), str(data.path))
        raise ValueError(f"task head2neck: unknown data kind '{data.kind}', expected synthetic or theta_seq")

    def _frames(self, theta: np.ndarray) -> dict[str, torch.Tensor]:
        theta = torch.as_tensor(theta, dtype=torch.float32)
        return {"rotations": axis_angle_to_matrix(theta), "head": head_rotations(self.rig, theta)}

    def batch(self, step: int, generator: torch.Generator) -> dict[str, torch.Tensor]:
        index = torch.randint(len(self.train["head"]), (int(self.cfg.task.batch_size),), generator=generator)
        return {name: value[index] for name, value in self.train.items()}

    # ------------------------------------------------------------------ loss

    def loss(self, batch: dict[str, torch.Tensor], step: int) -> tuple[torch.Tensor, dict[str, float]]:
        task = self.cfg.task
        theta = self.model(batch["head"])
        joint = 0.5 * ((axis_angle_to_matrix(theta) - batch["rotations"]) ** 2).sum((-1, -2)).mean()
        consistency = 0.5 * ((chain_head_rotation(theta, self.rig) - batch["head"]) ** 2).sum((-1, -2)).mean()
        e_rot = rotation_limit_energy(theta).mean()
        e_sim = adjacent_similarity_energy(theta, self.rig.parents).mean()
        loss = joint + task.lambda_fk * consistency + task.lambda_rot * e_rot + task.lambda_sim * e_sim
        joint, consistency, e_rot, e_sim = (float(x.detach()) for x in (joint, consistency, e_rot, e_sim))
        return loss, {"loss": float(loss.detach()), "joint_rms_deg": math.degrees(math.sqrt(joint)),
                      "head_rms_deg": math.degrees(math.sqrt(consistency)), "e_rot": e_rot, "e_sim": e_sim}

    # ------------------------------------------------------------------ evaluation

    @torch.no_grad()
    def evaluate(self, final: bool = False) -> dict[str, float]:
        head = self.val["head"]
        iterations = int(self.cfg.task.correction_iterations)
        raw = torch.cat([self.model(h) for h in head.split(8192)])
        rows = {"model": self._row(correct_to_head(raw, head, self.rig, iterations)), "model_raw": self._row(raw),
                **self._baseline_rows()}
        per_joint, head_max, inside = rows["model"]
        metrics = {"joint_err_deg": float(per_joint.mean()), "head_err_max_deg": head_max, "within_limits": inside}
        metrics.update({f"joint_err_deg_{n}": float(e) for n, e in zip(self.rig.joint_names, per_joint)})
        for name in ("model_raw", "uniform", "rom"):
            per_joint, head_max, inside = rows[name]
            metrics.update({f"{name}_joint_err_deg": float(per_joint.mean()), f"{name}_head_err_max_deg": head_max,
                            f"{name}_within_limits": inside})
        if final:
            self._print_table(rows, len(head))
        return metrics

    def _row(self, theta: torch.Tensor) -> tuple[torch.Tensor, float, float]:
        """(per-joint angular error [J] degrees, max head error degrees, share within limits) on val."""
        head, truth = self.val["head"], self.val["rotations"]
        per_joint = torch.rad2deg(relative_angle(axis_angle_to_matrix(theta), truth)).mean(0)
        return per_joint, float(head_error_deg(theta, head, self.rig).max()), float(within_limits(theta).float().mean())

    def _baseline_rows(self) -> dict[str, tuple]:
        """The uniform and ROM splits (with the same correction) on val: computed once, they do not learn."""
        if self._baselines is None:
            head = self.val["head"]
            rest = self.rig.anatomical_rest_rotations
            iterations = int(self.cfg.task.correction_iterations)
            self._baselines = {split: self._row(correct_to_head(split_head_rotation(head, rest, split), head,
                                                                self.rig, iterations))
                               for split in ("uniform", "rom")}
        return self._baselines

    def _print_table(self, rows: dict, frames: int) -> None:
        labels = {"model": "MLP + correction", "model_raw": "MLP (raw output)",
                  "uniform": "uniform split + correction", "rom": "ROM split + correction"}
        names = self.rig.joint_names
        print(f"\nhead2neck: per-joint angular error (deg) on {frames} held-out frames ({self.val_description})")
        print(f"{'method':27s}{'mean':>7s}" + "".join(f"{n:>7s}" for n in names) + f"{'head max':>10s}{'in limits':>11s}")
        for key, label in labels.items():
            per_joint, head_max, inside = rows[key]
            print(f"{label:27s}{float(per_joint.mean()):7.2f}" + "".join(f"{float(e):7.2f}" for e in per_joint)
                  + f"{head_max:10.1e}{inside:11.4f}")

    def model_config(self) -> dict:
        return self._model_config
