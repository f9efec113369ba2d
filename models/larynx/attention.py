"""Attention of the larynx transformer: ALiBi biases, banded (windowed causal) attention, the per-frame cache.

Every attention looks at a fixed window of past frames and its bias falls by ``slope_h`` per frame of offset
(ALiBi slopes 1/4 ... 1/256 per frame: time scales of 4 to 256 frames), so nothing depends on an absolute
position: the whole-sequence form (:func:`banded_attention`) and the one-frame form (:func:`attend_one` over a
:class:`WindowCache`) compute the same thing.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn


def alibi_slopes(n_heads: int) -> Tensor:
    """Per-head slopes 2^(-8h/H), h = 1..H (geometric, Press et al., "Train Short, Test Long", ICLR 2022)."""
    return torch.tensor([2.0 ** (-8.0 * (h + 1) / n_heads) for h in range(n_heads)])


def relative_bias(offsets: Tensor, slopes: Tensor, window: int) -> Tensor:
    """Attention bias from relative offsets: -slope_h * offset inside the window.

    offsets [Tq,Tk] long (query frame - key frame), slopes [H] -> bias [H,Tq,Tk]; -inf where the
    key is in the future (offset < 0) or outside the window (offset >= window).
    """
    inside = (offsets >= 0) & (offsets < window)
    bias = -slopes[:, None, None] * offsets.clamp(min=0).to(slopes.dtype)
    return bias.masked_fill(~inside, float("-inf"))


def banded_attention(q: Tensor, k: Tensor, v: Tensor, slopes: Tensor, window: int, chunk: int = 64) -> Tensor:
    """Causal attention of each query frame i to key frames i-window+1..i, in chunks of queries.

    q, k, v [B,H,T,dh] -> [B,H,T,dh]; memory O(T * (chunk + window)), no length limit.
    """
    length = q.shape[2]
    chunk = max(chunk, window)
    out = []
    for start in range(0, length, chunk):
        stop = min(length, start + chunk)
        first = max(0, start - window + 1)
        offsets = (torch.arange(start, stop, device=q.device)[:, None]
                   - torch.arange(first, stop, device=q.device)[None, :])
        bias = relative_bias(offsets, slopes, window).to(q.dtype)  # [H,chunk,keys]
        scores = torch.matmul(q[:, :, start:stop], k[:, :, first:stop].transpose(-1, -2)) * q.shape[-1] ** -0.5
        out.append(torch.matmul(torch.softmax(scores + bias, dim=-1), v[:, :, first:stop]))
    return torch.cat(out, dim=2)


def split_heads(x: Tensor, n_heads: int) -> Tensor:
    """[B,T,d] -> [B,H,T,d/H]."""
    return x.view(x.shape[0], x.shape[1], n_heads, -1).transpose(1, 2)


def merge_heads(x: Tensor) -> Tensor:
    """[B,H,T,d/H] -> [B,T,d]."""
    return x.transpose(1, 2).reshape(x.shape[0], x.shape[2], -1)


class WindowCache:
    """Keys and values of the last ``window`` frames, as [B,H,n,dh] views in frame order.

    Each frame is written twice, at slot ``t % window`` and ``t % window + window`` of a buffer of
    2 * window slots, so the last n frames are always the contiguous slice ending at slot
    ``t % window + window``: no copying or rolling, and memory fixed at 2 * window frames.
    """

    def __init__(self, batch: int, heads: int, head_dim: int, window: int, dtype=torch.float32, device=None):
        self.window = window
        self.kv = torch.zeros(2, batch, heads, 2 * window, head_dim, dtype=dtype, device=device)  # keys, values
        self.count = 0

    def append(self, kv: Tensor) -> tuple[Tensor, Tensor]:
        """Add frame ``count`` (kv [2,B,H,dh]); returns keys, values [B,H,n,dh] of the last n <= window frames."""
        slot = self.count % self.window
        self.kv[:, :, :, slot] = kv
        self.kv[:, :, :, slot + self.window] = kv
        self.count += 1
        n = min(self.count, self.window)
        recent = self.kv[:, :, :, slot + self.window + 1 - n: slot + self.window + 1]
        return recent[0], recent[1]


def attend_one(q: Tensor, keys: Tensor, values: Tensor, bias: Tensor) -> Tensor:
    """Attention of one query frame: q [B,H,dh], keys/values [B,H,n,dh], bias [B*H,n,1] -> [B,H*dh].

    Written with batched matrix products over B*H (views, no copies): per-frame decoding is
    dominated by the number of tensor operations, not by their size.
    """
    batch, heads, n, dh = keys.shape
    scores = torch.baddbmm(bias, keys.flatten(0, 1), q.reshape(batch * heads, dh, 1), alpha=dh ** -0.5)  # [B*H,n,1]
    weights = torch.softmax(scores, dim=1)
    return torch.bmm(weights.transpose(1, 2), values.flatten(0, 1)).view(batch, heads * dh)


def step_bias(slopes: Tensor, window: int, batch: int) -> Tensor:
    """Biases [B*H,window,1] of one query over keys at offsets window-1, ..., 0 (see :func:`attend_one`);
    the last n rows serve the first frames, when only n keys exist."""
    offsets = torch.arange(window - 1, -1, -1, device=slopes.device)[None, :]
    return relative_bias(offsets, slopes, window)[:, 0].repeat(batch, 1)[:, :, None]


class SelfAttention(nn.Module):
    """Causal self-attention over the last ``window`` frames with the ALiBi bias."""

    def __init__(self, d_model: int, n_heads: int, window: int):
        super().__init__()
        self.n_heads, self.window = n_heads, window
        self.register_buffer("slopes", alibi_slopes(n_heads), persistent=False)
        self.qkv = nn.Linear(d_model, 3 * d_model)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, x: Tensor) -> Tensor:
        """x [B,T,d] (normalised tokens) -> [B,T,d], frame t attending to frames t-window+1..t."""
        q, k, v = (split_heads(part, self.n_heads) for part in self.qkv(x).chunk(3, dim=-1))
        return self.out(merge_heads(banded_attention(q, k, v, self.slopes, self.window)))


class CrossAttention(nn.Module):
    """Attention of frame t to the encoded expressions of frame t alone (FaceFormer's alignment).

    With the aligned frame as the only key, attention returns its value: no query or keys are needed, ``kv``
    projects values only, and the output depends on the expressions alone.
    """

    def __init__(self, d_model: int):
        super().__init__()
        self.kv = nn.Linear(d_model, d_model)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, memory: Tensor) -> Tensor:
        """memory [B,T,d] encoded expressions -> [B,T,d]."""
        return self.out(self.kv(memory))
