"""Weights laid out for products with a single frame, LayerNorms folded in, the members of an ensemble stacked.

A live frame is some hundred operations on 64-wide vectors, and each costs its call more than its arithmetic:
calling a module, or reading a parameter through one, costs as much as a product.  So the per-frame versions of
the modules (``*_frame`` functions beside each module) compute from plain tensors taken once per stream, and the
K members of an ensemble (:mod:`.ensemble`) run in the same calls: every frame tensor carries the members first,
x [K,B,...], and a product is ``torch.baddbmm(bias [K,1,out], x [K,B,in], weight_t [K,in,out])``
(:func:`stacked`), which costs one member's call.  A single model is an ensemble of one.
"""
from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn


def affine(weight: Tensor, bias: Tensor, norm: nn.LayerNorm | None = None) -> tuple[Tensor, Tensor]:
    """``(bias, weight_t)`` of y = x W^T + b, computed as ``torch.addmm(bias, x, weight_t)``.

    With ``norm``, the LayerNorm before the product is folded in: W (g * n + beta) + b = (W g) n + (W beta + b)
    for the normalised n, so the norm runs without its affine part (:func:`normalise`).
    """
    weight, bias = weight.detach(), bias.detach()
    if norm is not None:
        bias = bias + weight @ norm.bias.detach()
        weight = weight * norm.weight.detach()
    return bias, weight.t()


def linear(layer: nn.Linear, norm: nn.LayerNorm | None = None) -> tuple[Tensor, Tensor]:
    """:func:`affine` of a linear layer (and the LayerNorm before it)."""
    return affine(layer.weight, layer.bias, norm)


def stacked(members: list[tuple[Tensor, Tensor]]) -> tuple[Tensor, Tensor]:
    """The members' ``(bias [out], weight_t [in,out])`` (:func:`affine`) -> ``(bias [K,1,out], weight_t [K,in,out])``
    for ``torch.baddbmm(bias, x [K,B,in], weight_t)``."""
    return torch.stack([bias for bias, _ in members])[:, None], torch.stack([weight for _, weight in members])


def normalise(x: Tensor, eps: float) -> Tensor:
    """LayerNorm without its affine part over the last dimension (folded into the next product, :func:`affine`)."""
    return F.layer_norm(x, x.shape[-1:], None, None, eps)
