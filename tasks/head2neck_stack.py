"""Many head2neck MLPs trained at once: the inner loop of the calibration's cross-validation.

The calibration (``tasks.head2neck_calibration``) trains a few dozen small runs (candidate x fold) on a few
hundred frames; one run at a time costs ~25 ms a step on one CPU thread whatever the batch (the loss is
dozens of small tensor operations).  Here K models of one architecture are stacked (``[K, ...]`` weights,
batched matrix products) and trained on one joint batch, so the per-operation cost is paid once a step.

Each member is exactly what one :class:`models.head2neck.Head2NeckMLP` trained alone would be: its loss is
its own batch's mean (:func:`pose_loss`, the task's loss), the loss summed over members gives each its own
gradient, gradients are clipped per member (``torch.nn.utils.clip_grad_norm_``'s rule), and AdamW acts
element by element.  The learning rate warms up linearly over ``warmup_steps`` and then stays constant, so a
snapshot after ``L`` steps is what a run of ``L`` steps gives (the final training repeats the chosen run).

Inputs are precomputed per frame (the base split and the MLP features depend on the head alone): a
:class:`FrameBank` holds them with the target rotations.  ``extra`` feature columns (the head's recent
motion, measured in ``benchmarks/bench_head2neck.py``) enter the first layer through zero-initialised
weights, so a member started from a shipped model starts as that model.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import nn

from base.rotations import axis_angle_to_matrix, matrix_to_rot6d, relative_angle
from data.cervical_prior import head_rotations
from data.joint_limits import adjacent_similarity_energy, rotation_limit_energy
from models.head2neck import ACTIVATIONS, Head2NeckMLP, chain_head_rotation, correct_to_head, split_head_rotation


def pose_loss(theta: torch.Tensor, rotations: torch.Tensor, head: torch.Tensor, rig, lambda_fk: float,
              lambda_rot: float, lambda_sim: float) -> tuple[torch.Tensor, dict[str, float]]:
    """The head2neck loss of predicted anatomical theta [B,J,3] against target rotations [B,J,3,3] and heads
    [B,3,3]: ``mean_j |R_j - R_j*|^2 / 2 + lambda_fk |H(theta) - H*|^2 / 2 + lambda_rot E_rot + lambda_sim
    E_sim``, means over the batch; (loss, its terms as floats)."""
    joint = 0.5 * ((axis_angle_to_matrix(theta) - rotations) ** 2).sum((-1, -2)).mean()
    consistency = 0.5 * ((chain_head_rotation(theta, rig) - head) ** 2).sum((-1, -2)).mean()
    e_rot = rotation_limit_energy(theta).mean()
    e_sim = adjacent_similarity_energy(theta, rig.parents).mean()
    loss = joint + lambda_fk * consistency + lambda_rot * e_rot + lambda_sim * e_sim
    joint, consistency, e_rot, e_sim = (float(x.detach()) for x in (joint, consistency, e_rot, e_sim))
    return loss, {"loss": float(loss.detach()), "joint_rms_deg": math.degrees(math.sqrt(joint)),
                  "head_rms_deg": math.degrees(math.sqrt(consistency)), "e_rot": e_rot, "e_sim": e_sim}


@dataclass
class FrameBank:
    """Frames [N] with what training and scoring read: target rotations [N,J,3,3], heads [N,3,3], the base
    split [N,J,3] and the MLP's input features [N,F] (6 + extra columns)."""

    rotations: torch.Tensor
    head: torch.Tensor
    base: torch.Tensor
    features: torch.Tensor

    @classmethod
    def build(cls, theta: torch.Tensor, rig, model: Head2NeckMLP, extra: torch.Tensor | None = None) -> FrameBank:
        """The bank of anatomical theta [N,J,3] on ``rig`` for models of ``model``'s configuration."""

        theta = torch.as_tensor(theta, dtype=torch.float32)
        head = head_rotations(rig, theta)
        with torch.no_grad():
            base = split_head_rotation(head, rig.anatomical_rest_rotations, model.config.base)
            features = (matrix_to_rot6d(head) - model.identity.to(head)) * model.input_scale
        if extra is not None:
            features = torch.cat([features, torch.as_tensor(extra, dtype=torch.float32)], 1)
        return cls(axis_angle_to_matrix(theta), head, base, features)

    def __len__(self) -> int:
        return len(self.head)

    def cat(self, other: FrameBank) -> FrameBank:
        return FrameBank(*(torch.cat([getattr(self, n), getattr(other, n)]) for n in
                           ("rotations", "head", "base", "features")))


class StackedMLP:
    """K copies of one Head2NeckMLP architecture as stacked tensors (weights [K,in,out], biases [K,out])."""

    def __init__(self, models: list[Head2NeckMLP], extra_inputs: int = 0):
        config = models[0].config
        if any(m.config != config for m in models):
            raise ValueError("a stack holds models of one configuration")
        self.config, self.num_joints = config, models[0].num_joints
        self.activation = ACTIVATIONS[config.activation]()
        self.weights, self.biases = [], []
        for i, layers in enumerate(zip(*[[x for x in m.mlp if isinstance(x, nn.Linear)] for m in models])):
            weight = torch.stack([layer.weight.detach().T for layer in layers]).clone()     # [K,in,out]
            if i == 0 and extra_inputs:
                weight = torch.cat([weight, weight.new_zeros(len(models), extra_inputs, weight.shape[2])], 1)
            self.weights.append(weight.requires_grad_(True))
            self.biases.append(torch.stack([layer.bias.detach() for layer in layers]).clone().requires_grad_(True))

    def parameters(self) -> list[torch.Tensor]:
        return [*self.weights, *self.biases]

    def __len__(self) -> int:
        return len(self.weights[0])

    def __call__(self, base: torch.Tensor, features: torch.Tensor) -> torch.Tensor:
        """base [K,B,J,3], features [K,B,F] -> anatomical theta [K,B,J,3] before the correction."""
        x = features
        for i, (weight, bias) in enumerate(zip(self.weights, self.biases)):
            x = torch.baddbmm(bias[:, None, :], x, weight)
            if i < len(self.weights) - 1:
                x = self.activation(x)
        return base + self.config.residual_scale * x.reshape(*base.shape)

    def member(self, k: int) -> Head2NeckMLP:
        """Member k as a Head2NeckMLP (only for stacks without extra inputs)."""
        if self.weights[0].shape[1] != 6:
            raise ValueError("a member with extra inputs is not a Head2NeckMLP")
        model = Head2NeckMLP(self.config, self.num_joints)
        layers = [x for x in model.mlp if isinstance(x, nn.Linear)]
        with torch.no_grad():
            for layer, weight, bias in zip(layers, self.weights, self.biases):
                layer.weight.copy_(weight[k].T)
                layer.bias.copy_(bias[k])
        return model.eval()


@dataclass
class Member:
    """One run of a stack: the bank indices it trains on (its frames, and the prior's), the prior's share of
    each batch, and the indices it is scored on after each length (may be empty)."""

    train: torch.Tensor
    prior: torch.Tensor
    prior_weight: float
    score: torch.Tensor


@dataclass
class StackSettings:
    """How a stack trains (the calibration's ``data.calibration`` settings)."""

    batch_size: int
    lr: float
    warmup_steps: int
    grad_clip: float
    lambda_fk: float
    lambda_rot: float
    lambda_sim: float


@torch.no_grad()
def member_errors(stack: StackedMLP, bank: FrameBank, members: list[Member], rig) -> list[torch.Tensor]:
    """Each member's per-frame error on its ``score`` frames: the mean over joints of the angle (degrees) between
    its corrected prediction and the target (the task's ``joint_err_deg`` before the mean over frames)."""
    predictions = []
    for k, member in enumerate(members):
        index = member.score
        single = StackedMLP.__new__(StackedMLP)
        single.__dict__.update(stack.__dict__)
        single.weights = [w[k:k + 1] for w in stack.weights]
        single.biases = [b[k:k + 1] for b in stack.biases]
        predictions.append(single(bank.base[index][None], bank.features[index][None])[0])
    index = torch.cat([m.score for m in members])
    if not len(index):
        return [torch.zeros(0) for _ in members]
    theta = correct_to_head(torch.cat(predictions), bank.head[index], rig)
    error = torch.rad2deg(relative_angle(axis_angle_to_matrix(theta), bank.rotations[index])).mean(-1)
    return list(error.split([len(m.score) for m in members]))


def train_stack(stack: StackedMLP, bank: FrameBank, members: list[Member], rig, settings: StackSettings,
                lengths: list[int], seed: int) -> dict[int, list[torch.Tensor]]:
    """Train every member for ``max(lengths)`` steps; {length: each member's per-frame errors on its score
    frames after that many steps} (length 0: the start)."""
    generator = torch.Generator().manual_seed(seed)
    optimizer = torch.optim.AdamW(stack.parameters(), lr=settings.lr, weight_decay=0.0, fused=True)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: min(1.0, (s + 1) / settings.warmup_steps) if settings.warmup_steps else 1.0)
    size, k = int(settings.batch_size), len(members)
    scores = {0: member_errors(stack, bank, members, rig)} if 0 in lengths else {}
    for step in range(max(lengths, default=0)):
        index = torch.stack([_draw(m, size, generator) for m in members])                       # [K,B]
        theta = stack(bank.base[index], bank.features[index]).reshape(k * size, -1, 3)
        flat = index.reshape(-1)
        loss, _ = pose_loss(theta, bank.rotations[flat], bank.head[flat], rig, settings.lambda_fk,
                            settings.lambda_rot, settings.lambda_sim)
        optimizer.zero_grad(set_to_none=True)
        (loss * k).backward()   # the sum of the members' own batch means
        if settings.grad_clip:
            _clip_per_member(stack.parameters(), settings.grad_clip)
        optimizer.step()
        schedule.step()
        if step + 1 in lengths:
            scores[step + 1] = member_errors(stack, bank, members, rig)
    return scores


def _draw(member: Member, size: int, generator: torch.Generator) -> torch.Tensor:
    """A batch of ``size`` bank indices: ``round(size * prior_weight)`` from the prior, the rest from the files."""
    from_prior = int(round(size * member.prior_weight)) if len(member.prior) else 0
    own = member.train[torch.randint(len(member.train), (size - from_prior,), generator=generator)]
    if not from_prior:
        return own
    return torch.cat([own, member.prior[torch.randint(len(member.prior), (from_prior,), generator=generator)]])


def _clip_per_member(parameters: list[torch.Tensor], max_norm: float) -> None:
    """Scale each member's gradient to a norm of at most ``max_norm`` (clip_grad_norm_ on each member alone)."""
    squares = sum(p.grad.reshape(len(p.grad), -1).pow(2).sum(1) for p in parameters)
    factor = (max_norm / (squares.sqrt() + 1e-6)).clamp(max=1.0)
    for p in parameters:
        p.grad.mul_(factor.reshape(-1, *([1] * (p.grad.ndim - 1))))
