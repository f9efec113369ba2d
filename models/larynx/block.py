"""The larynx transformer's decoder block, whole sequences (:class:`Block`) and one frame (:func:`block_frame`).

Pre-norm: ALiBi-biased causal self-attention over ``window`` frames, the aligned cross-attention, an MLP.
:func:`block_frame` is ``Block.forward`` (eval mode) for one frame, from a snapshot of the block's weights
(:class:`BlockFrameWeights`) and its self-attention cache (:class:`BlockState`).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .attention import CrossAttention, SelfAttention, WindowCache, alibi_slopes, attend_one, step_bias
from .config import LarynxTransformerConfig
from .folding import affine, linear, normalise, stacked


class Block(nn.Module):
    """Pre-norm decoder block: ALiBi-biased causal self-attention, aligned cross-attention, MLP."""

    def __init__(self, cfg: LarynxTransformerConfig):
        super().__init__()
        d = cfg.d_model
        self.ln_self, self.ln_mlp = nn.LayerNorm(d), nn.LayerNorm(d)
        self.attention = SelfAttention(d, cfg.n_heads, cfg.window)
        self.cross = CrossAttention(d)
        self.mlp = nn.Sequential(nn.Linear(d, cfg.d_ff), nn.GELU(approximate="tanh"), nn.Linear(cfg.d_ff, d))
        self.dropout = nn.Dropout(cfg.dropout)

    def forward(self, x: Tensor, memory: Tensor) -> Tensor:
        """x [B,T,d] tokens, memory [B,T,d] encoded expressions -> [B,T,d]."""
        x = x + self.dropout(self.attention(self.ln_self(x)))
        x = x + self.dropout(self.cross(memory))
        return x + self.dropout(self.mlp(self.ln_mlp(x)))


class BlockFrameWeights:
    """The members' :class:`Block` weights for :func:`block_frame`, stacked (:mod:`.folding`): each LayerNorm folded
    into the product after it, the cross-attention's value and output projections multiplied into one."""

    def __init__(self, blocks: list[Block]):
        first = blocks[0]
        with torch.no_grad():
            self.heads = first.attention.n_heads
            self.self_eps = first.ln_self.eps
            self.qkv = stacked([linear(b.attention.qkv, b.ln_self) for b in blocks])
            self.self_out = stacked([linear(b.attention.out) for b in blocks])
            self.cross = stacked([affine(b.cross.out.weight @ b.cross.kv.weight,
                                         b.cross.out.weight @ b.cross.kv.bias + b.cross.out.bias) for b in blocks])
            self.mlp_eps = first.ln_mlp.eps
            self.mlp_in = stacked([linear(b.mlp[0], b.ln_mlp) for b in blocks])
            self.mlp_out = stacked([linear(b.mlp[2]) for b in blocks])


@dataclass
class BlockState:
    """A block's decoding state: its self-attention cache and the biases [K*B*H,window,1] of one query over it
    (the members' K streams of B are one batch of K*B to the cache)."""

    self_cache: WindowCache
    self_bias: Tensor

    @classmethod
    def start(cls, batch: int, heads: int, head_dim: int, window: int, dtype, device) -> BlockState:
        """The state before frame 0: an empty cache."""
        slopes = alibi_slopes(heads).to(device)
        return cls(WindowCache(batch, heads, head_dim, window, dtype, device),
                   step_bias(slopes, window, batch).to(dtype))


def cross_frame(weights: BlockFrameWeights, memory: Tensor) -> Tensor:
    """The cross-attention's output [K,B,d] for one frame's encoded expressions memory [K,B,d]."""
    return torch.baddbmm(weights.cross[0], memory, weights.cross[1])


def block_frame(weights: BlockFrameWeights, state: BlockState, x: Tensor, cross: Tensor) -> Tensor:
    """``Block.forward`` (eval mode) of every member for the next frame: its token x [K,B,d] and cross-attention
    output cross [K,B,d] (:func:`cross_frame`) -> [K,B,d]; appends the frame's keys and values to ``state``'s
    cache."""
    members, batch = x.shape[:2]
    qkv = torch.baddbmm(weights.qkv[0], normalise(x, weights.self_eps), weights.qkv[1])
    qkv = qkv.view(members * batch, 3, weights.heads, -1)
    keys, values = state.self_cache.append(qkv[:, 1:].transpose(0, 1))
    attended = attend_one(qkv[:, 0], keys, values, state.self_bias[:, -keys.shape[2]:]).view(members, batch, -1)
    x = x + torch.baddbmm(weights.self_out[0], attended, weights.self_out[1])
    x = x + cross
    hidden = F.gelu(torch.baddbmm(weights.mlp_in[0], normalise(x, weights.mlp_eps), weights.mlp_in[1]),
                    approximate="tanh")
    return x + torch.baddbmm(weights.mlp_out[0], hidden, weights.mlp_out[1])
