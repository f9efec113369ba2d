"""Expression -> larynx transformer (after FaceFormer) with a streaming decoder of bounded cost.

FaceFormer (Fan et al., CVPR 2022) regresses motion autoregressively: past motion frames are the
decoder's tokens (plus a periodic positional encoding and a style embedding), causal
self-attention has an ALiBi-style periodic bias, and the driving signal enters through
cross-attention aligned frame to frame.  Here the motion is the larynx slide tau and the
driving signal is the expression sequence psi.  Unlike FaceFormer's code, nothing depends on an
absolute length: the positional encoding is periodic, the attention biases are computed from
relative offsets, and every attention looks at a fixed window of past frames, so

- the teacher-forced ``forward`` runs banded attention chunk by chunk (memory O(T * window));
- :class:`LarynxStream` decodes frame by frame with a key/value cache of ``window`` frames:
  each frame costs the same at frame 100 as at frame 100,000 and memory is bounded;
- ``generate_uncached`` is FaceFormer's decoding (recompute the whole prefix at every frame),
  kept as the reference the cache must match.

Paired captures come in minutes, not hours, and the defaults (:class:`LarynxTransformerConfig`) are
chosen for that regime on real expressions (``benchmarks/bench_larynx_real.py``; figures in
``benchmarks/README.md``):
- the expression encoder is a stack of dilated causal convolutions (a receptive field of
  ``1 + (kernel-1) * sum(dilations)`` frames, about two seconds), a residual GRU layer (memory beyond
  any window: a swallow in progress, the time since the last one, effort building up over seconds;
  one cell step per live frame) and a bank of learnt first-order low-passes (:class:`Smoothing`: the
  larynx's inertia is one); its features are added to the decoder's tokens, so the self-attention
  window sees past expressions, not only past tau;
- a per-subject output gain (``style_gain``) beside the additive style: people differ by how far
  their larynx moves for the same face, a product;
- ``period`` 1: the attention bias falls per frame (ALiBi slopes 1/4 ... 1/256 per frame: time
  scales of 4 to 256 frames) and the positional encoding is constant; FaceFormer's period of
  speech-animation frames (25 at 25 fps) has no counterpart in the larynx;
- ``feedback`` off: feeding the previous tau back (FaceFormer's autoregression) is available, but at
  inference that tau is the model's own prediction, a function of the psi the tokens already see; on
  takes unlike the training ones it drifts;
- one decoder block (as FaceFormer) and dropout 0.1;
- no LayerNorm before the head (``output_norm``): the head reads the residual stream as it is, so a face that
  moves further than the training takes did can move tau further (a norm there gives every frame one size).

Conventions (shapes carry a batch B and frames T):
- psi [B,T,55]: expression weights in ``data.expressions.EXPRESSION_NAMES`` order, at
  ``model.fps`` frames per second (the rate of the training data);
- tau [B,T]: larynx slide in UV units of the larynx map, + = up the neck (``data.synthetic_tau``).
  Inside the network tau is normalised, ``(tau - tau_mean) / tau_scale`` (both from the data);
- ``previous_tau`` [B,T]: the tau fed to frame t, i.e. tau of frame t-1 (``tau_mean`` at t = 0),
  see :meth:`LarynxTransformer.shift`;
- frame t's prediction depends on psi[:, :t+1] and previous_tau[:, :t+1] only (causal);
- subject [B] long: index into the style table, 0 = unknown subject (average style); names are
  ``model.subjects`` (index i+1 is ``subjects[i]``);
- eta [B]: larynx size, an input only when ``use_eta`` (1 = template size).
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from base.cli import register_config
from base.errors import InputError
from base.threads import single_thread
from data.expressions import NUM_EXPRESSIONS


@dataclass
class LarynxTransformerConfig:
    """The sizes of the network (hydra's ``model`` group of ``task=larynx_transformer``).

    The defaults are chosen for a few thousand to a few tens of thousands of training frames at 30 fps
    (``benchmarks/README.md``, "Expression -> larynx").
    """

    d_model: int = 64
    n_heads: int = 4
    n_layers: int = 1          # decoder blocks (FaceFormer uses one)
    d_ff: int = 128            # hidden width of each block's MLP
    window: int = 64           # frames each self-attention sees (the key/value cache size)
    cross_window: int = 1      # expression frames frame t cross-attends to (1 = the aligned frame, as FaceFormer)
    period: int = 1            # frames: period of the positional encoding and of the attention bias
    expression_kernel: int = 3
    # Dilation of each causal convolution of the expression encoder; the receptive field is
    # 1 + (expression_kernel - 1) * sum(expression_dilations) frames.
    expression_dilations: list[int] = field(default_factory=lambda: [1, 2, 4, 8, 16])
    # Longest initial time constant (frames) of the encoder's bank of learnt low-passes (0: none).
    smoothing_frames: float = 128.0
    # A gated recurrent layer (GRU, residual) after the convolutions: state of unbounded memory at a flat
    # per-frame cost (a swallow in progress, a refractory time, an effort that builds up over seconds).
    recurrent: bool = True
    dropout: float = 0.1       # on the expression features, attention outputs and MLP outputs
    # Feed the previous frame's tau back into the tokens (FaceFormer's autoregression).  At inference the
    # fed-back tau is the model's own prediction, a function of the past psi the tokens already see, so it
    # adds no information, only drift on takes unlike the training ones (benchmarks/README.md).
    feedback: bool = False
    use_eta: bool = False      # feed the larynx size eta to the motion encoder
    # Levels of each expression weight where the input layer may bend (:func:`hinge_features`): the larynx
    # answers some poses past a level (a jaw that is shut, lips pressed), and a hinge per level lets the
    # first product express that per channel.  [] = psi enters linearly.
    input_knots: list[float] = field(default_factory=list)
    # A LayerNorm before the head (as GPT's final norm).  It rescales every frame's features to one size, so how far
    # the face moves past what training showed cannot move tau further; without it the head reads the residual
    # stream as it is (real-regime benchmark, seeds 0-3: equal or better on every family, benchmarks/README.md).
    output_norm: bool = False

    def __post_init__(self) -> None:
        if self.d_model % self.n_heads or (self.d_model // self.n_heads) % 2:
            raise ValueError(f"d_model {self.d_model} must split into {self.n_heads} heads of even size")
        for name in ("n_layers", "d_ff", "window", "cross_window", "period", "expression_kernel"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if any(int(d) < 1 for d in self.expression_dilations):
            raise ValueError(f"expression_dilations must be positive, got {list(self.expression_dilations)}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")

    @property
    def receptive_field(self) -> int:
        """Frames of psi the expression encoder's output at frame t depends on (t and before)."""
        return 1 + (self.expression_kernel - 1) * sum(int(d) for d in self.expression_dilations)


@dataclass
class LarynxDataFields:
    """What the model takes from its training data (filled in by the task, stored in the checkpoint)."""

    fps: float                 # frames per second of psi and tau
    subjects: list[str]        # training subject names: style index i+1 is subjects[i], 0 the unknown subject
    tau_mean: float            # tau normalisation (UV units)
    tau_scale: float


register_config("larynx_transformer_schema", LarynxTransformerConfig, group="model")

SIZES = tuple(f.name for f in dataclasses.fields(LarynxTransformerConfig))
DATA_KEYS = tuple(f.name for f in dataclasses.fields(LarynxDataFields))


def hinge_features(psi: Tensor, knots: Tensor) -> Tensor:
    """psi [...,C] and knots [K] -> [...,C*(K+1)]: per channel c, psi_c then relu(psi_c - knot_k) for each knot
    (channel-major: the K+1 features of channel c are columns c*(K+1) ... c*(K+1)+K)."""
    if not len(knots):
        return psi
    bends = torch.relu(psi[..., None] - knots)
    return torch.cat([psi[..., None], bends], dim=-1).flatten(-2)


def alibi_slopes(n_heads: int) -> Tensor:
    """Per-head slopes 2^(-8h/H), h = 1..H (geometric, Press et al., "Train Short, Test Long", ICLR 2022)."""
    return torch.tensor([2.0 ** (-8.0 * (h + 1) / n_heads) for h in range(n_heads)])


def relative_bias(offsets: Tensor, slopes: Tensor, period: int, window: int) -> Tensor:
    """Attention bias from relative offsets: -slope_h * floor(offset / period) inside the window.

    offsets [Tq,Tk] long (query frame - key frame), slopes [H] -> bias [H,Tq,Tk]; -inf where the
    key is in the future (offset < 0) or outside the window (offset >= window).
    """
    inside = (offsets >= 0) & (offsets < window)
    steps = torch.div(offsets.clamp(min=0), period, rounding_mode="floor").to(slopes.dtype)
    bias = -slopes[:, None, None] * steps
    return bias.masked_fill(~inside, float("-inf"))


def periodic_encoding(positions: Tensor, d_model: int, period: int) -> Tensor:
    """Sinusoidal encoding of ``positions mod period``: positions [T] long -> [T, d_model]."""
    phase = (positions % period).to(torch.float32)[:, None]
    freqs = torch.exp(torch.arange(0, d_model, 2, dtype=torch.float32) * (-math.log(10000.0) / d_model))
    out = torch.zeros(len(positions), d_model)
    out[:, 0::2] = torch.sin(phase * freqs)
    out[:, 1::2] = torch.cos(phase * freqs[: d_model // 2])
    return out


def banded_attention(q: Tensor, k: Tensor, v: Tensor, slopes: Tensor, period: int, window: int,
                     chunk: int = 64) -> Tensor:
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
        bias = relative_bias(offsets, slopes, period, window).to(q.dtype)  # [H,chunk,keys]
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


def step_bias(slopes: Tensor, period: int, window: int, batch: int) -> Tensor:
    """Biases [B*H,window,1] of one query over keys at offsets window-1, ..., 0 (see :func:`attend_one`);
    the last n rows serve the first frames, when only n keys exist."""
    offsets = torch.arange(window - 1, -1, -1, device=slopes.device)[None, :]
    return relative_bias(offsets, slopes, period, window)[:, 0].repeat(batch, 1)[:, :, None]


class SelfAttention(nn.Module):
    """Causal self-attention over the last ``window`` frames with the periodic ALiBi-style bias."""

    def __init__(self, d_model: int, n_heads: int, window: int, period: int):
        super().__init__()
        self.n_heads, self.window, self.period = n_heads, window, period
        self.register_buffer("slopes", alibi_slopes(n_heads), persistent=False)
        self.qkv = nn.Linear(d_model, 3 * d_model)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, x: Tensor) -> Tensor:
        """x [B,T,d] (normalised tokens) -> [B,T,d], frame t attending to frames t-window+1..t."""
        q, k, v = (split_heads(part, self.n_heads) for part in self.qkv(x).chunk(3, dim=-1))
        return self.out(merge_heads(banded_attention(q, k, v, self.slopes, self.period, self.window)))


class CrossAttention(nn.Module):
    """Attention of frame t to the encoded expressions of frames t-cross_window+1..t (bias -slope * offset).

    With a one-frame window the only key is the aligned frame: attention returns its value, so neither a
    query nor keys are needed and ``kv`` projects values only.
    """

    def __init__(self, d_model: int, n_heads: int, window: int):
        super().__init__()
        self.n_heads, self.window = n_heads, window
        self.register_buffer("slopes", alibi_slopes(n_heads), persistent=False)
        self.norm = nn.LayerNorm(d_model) if window > 1 else None
        self.q = nn.Linear(d_model, d_model) if window > 1 else None
        self.kv = nn.Linear(d_model, (2 if window > 1 else 1) * d_model)
        self.out = nn.Linear(d_model, d_model)

    def forward(self, x: Tensor, memory: Tensor) -> Tensor:
        """x [B,T,d] tokens, memory [B,T,d] encoded expressions -> [B,T,d]."""
        if self.window == 1:
            return self.out(self.kv(memory))
        q = split_heads(self.q(self.norm(x)), self.n_heads)
        k, v = (split_heads(part, self.n_heads) for part in self.kv(memory).chunk(2, dim=-1))
        return self.out(merge_heads(banded_attention(q, k, v, self.slopes, 1, self.window)))

    def encode(self, memory: Tensor) -> list[Tensor]:
        """What :meth:`step` needs of C encoded frames memory [B,C,d]: per frame the output [B,d] (window 1,
        which does not depend on the query) or the keys and values [2,B,H,dh] for the cache."""
        if self.window == 1:
            return list(self.out(self.kv(memory)).unbind(1))
        k, v = (split_heads(part, self.n_heads) for part in self.kv(memory).chunk(2, dim=-1))  # [B,H,C,dh]
        return list(torch.stack([k, v]).unbind(3))


class Block(nn.Module):
    """Pre-norm decoder block: periodic-biased causal self-attention, aligned cross-attention, MLP.

    ``forward`` runs whole sequences (teacher forcing); :class:`LarynxStream` runs the same computation one
    frame at a time from a snapshot of these weights (:class:`FrameWeights`).
    """

    def __init__(self, cfg: LarynxTransformerConfig):
        super().__init__()
        d = cfg.d_model
        self.ln_self, self.ln_mlp = nn.LayerNorm(d), nn.LayerNorm(d)
        self.attention = SelfAttention(d, cfg.n_heads, cfg.window, cfg.period)
        self.cross = CrossAttention(d, cfg.n_heads, cfg.cross_window)
        self.mlp = nn.Sequential(nn.Linear(d, cfg.d_ff), nn.GELU(approximate="tanh"), nn.Linear(cfg.d_ff, d))
        self.dropout = nn.Dropout(cfg.dropout)

    def forward(self, x: Tensor, memory: Tensor) -> Tensor:
        """x [B,T,d] tokens, memory [B,T,d] encoded expressions -> [B,T,d]."""
        x = x + self.dropout(self.attention(self.ln_self(x)))
        x = x + self.dropout(self.cross(x, memory))
        return x + self.dropout(self.mlp(self.ln_mlp(x)))


@dataclass
class BlockState:
    """A block's decoding state in a :class:`LarynxStream`: its caches and their attention biases."""

    self_cache: WindowCache
    self_bias: Tensor
    cross_cache: WindowCache | None = None
    cross_bias: Tensor | None = None


class CausalConv(nn.Module):
    """Dilated temporal convolution over past frames only:
    y[t] = sum_j W_j x[t - (kernel-1-j) * dilation] (zeros before frame 0)."""

    def __init__(self, channels: int, kernel: int, dilation: int):
        super().__init__()
        self.dilation = dilation
        self.history = (kernel - 1) * dilation  # past frames each output needs
        self.conv = nn.Conv1d(channels, channels, kernel, dilation=dilation)

    def forward(self, x: Tensor, history: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """x [B,T,C], history [B,self.history,C] (the frames before x; zeros if None) -> (y [B,T,C], the history
        after x)."""
        if history is None:
            history = x.new_zeros(x.shape[0], self.history, x.shape[2])
        joined = torch.cat([history, x], dim=1)
        after = joined[:, joined.shape[1] - self.history:]
        return self.conv(joined.transpose(1, 2)).transpose(1, 2), after


class Smoothing(nn.Module):
    """A bank of causal first-order low-passes (exponential moving averages), one per channel, with learnt
    time constants: y[t] = a * y[t-1] + (1 - a) * x[t], a = exp(-1 / tau_c) (as Mega's moving-average
    attention, Ma et al., ICLR 2023).  The larynx's inertia and lag are low-passes of this kind; a window
    of attention can only approximate them.  Time constants start log-spaced from 1 frame to
    ``max_frames``; the smoothed channels are mixed back into the input (residual).

    The state before the first frame is the first frame itself (a recording starts at rest, not at zero).
    """

    def __init__(self, channels: int, max_frames: float, chunk: int = 128):
        super().__init__()
        self.chunk = chunk
        self.log_time = nn.Parameter(torch.linspace(0.0, math.log(max_frames), channels))
        self.mix = nn.Linear(channels, channels)

    def decay(self) -> Tensor:
        """a [C] per channel."""
        return torch.exp(-torch.exp(-self.log_time))

    def forward(self, x: Tensor, state: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """x [B,T,C] and the smoothed value [B,C] of the frame before (None: start at x's first frame) ->
        (x + mix(smoothed) [B,T,C], the smoothed value of the last frame [B,C])."""
        a = self.decay()
        state = x[:, 0] if state is None else state
        out = []
        for start in range(0, x.shape[1], self.chunk):  # exact recurrence as a [C,n,n] lower-triangular matrix
            part = x[:, start:start + self.chunk]
            k = torch.arange(part.shape[1], device=x.device)
            lag = (k[:, None] - k[None, :]).clamp(min=0).to(x.dtype)
            weights = torch.where(k[:, None] >= k[None, :], a[:, None, None] ** lag, 0.0) * (1 - a)[:, None, None]
            smoothed = torch.einsum("ctj,bjc->btc", weights, part)
            smoothed = smoothed + a[None, None, :] ** (k + 1).to(x.dtype)[None, :, None] * state[:, None, :]
            state = smoothed[:, -1]
            out.append(smoothed)
        return x + self.mix(torch.cat(out, dim=1)), state


@dataclass
class EncoderState:
    """What the expression encoder carries between calls: per convolution its last inputs
    [B,conv.history,d], the recurrent layer's hidden state [1,B,d] and the smoothing's last value [B,d]
    (None before the first frame)."""

    conv: list[Tensor]
    smooth: Tensor | None = None
    recurrent: Tensor | None = None


class ExpressionEncoder(nn.Module):
    """psi [B,T,55] -> features [B,T,d]: a linear projection, residual dilated causal convolutions, a residual
    GRU layer (with ``recurrent``), a bank of learnt low-passes (:class:`Smoothing`, with ``smoothing_frames``
    > 0), a norm."""

    def __init__(self, cfg: LarynxTransformerConfig):
        super().__init__()
        d = cfg.d_model
        self.register_buffer("knots", torch.tensor([float(k) for k in cfg.input_knots]), persistent=False)
        self.project = nn.Linear(NUM_EXPRESSIONS * (len(cfg.input_knots) + 1), d)
        self.temporal = nn.ModuleList(CausalConv(d, cfg.expression_kernel, int(dilation))
                                      for dilation in cfg.expression_dilations)
        self.recurrent = nn.GRU(d, d, batch_first=True) if cfg.recurrent else None
        self.smoothing = Smoothing(d, cfg.smoothing_frames) if cfg.smoothing_frames > 0 else None
        self.norm = nn.LayerNorm(d)
        self.dropout = nn.Dropout(cfg.dropout)

    def initial_state(self, batch_size: int, dtype=torch.float32) -> EncoderState:
        """The state before frame 0 (zeros before the convolutions, no smoothed value yet), on the weights' device."""
        d, device = self.project.out_features, self.project.weight.device
        return EncoderState([torch.zeros(batch_size, conv.history, d, dtype=dtype, device=device)
                             for conv in self.temporal])

    def forward(self, psi: Tensor, state: EncoderState | None = None) -> tuple[Tensor, EncoderState]:
        """Encode psi [B,T,55], the frames after ``state`` (None: from frame 0).

        Returns (features [B,T,d], the state after these frames).
        """
        x = self.project(hinge_features(psi, self.knots))
        conv_history = []
        for i, conv in enumerate(self.temporal):
            y, after = conv(x, None if state is None else state.conv[i])
            conv_history.append(after)
            y = F.gelu(y, approximate="tanh")
            x = x + (self.dropout(y) if self.training else y)
        hidden = None
        if self.recurrent is not None:
            y, hidden = self.recurrent(x, None if state is None else state.recurrent)
            x = x + (self.dropout(y) if self.training else y)
        smooth = None
        if self.smoothing is not None:
            x, smooth = self.smoothing(x, None if state is None else state.smooth)
        x = self.norm(x)
        return (self.dropout(x) if self.training else x), EncoderState(conv_history, smooth, hidden)


class LarynxTransformer(nn.Module):
    """tau from psi: autoregressive over tau, cross-attending to the expressions (see module docstring).

    Args:
        cfg: the network's sizes.
        data: what it takes from the training data (rate, subjects, tau normalisation).
    """

    def __init__(self, cfg: LarynxTransformerConfig, data: LarynxDataFields):
        super().__init__()
        self.cfg, self.data = cfg, data
        d = cfg.d_model
        self.fps = float(data.fps)
        self.window, self.cross_window, self.period = cfg.window, cfg.cross_window, cfg.period
        self.subjects = [str(s) for s in data.subjects]
        self.use_eta, self.feedback = bool(cfg.use_eta), bool(cfg.feedback)
        self.register_buffer("tau_mean", torch.tensor(float(data.tau_mean)), persistent=False)
        self.register_buffer("tau_scale", torch.tensor(float(data.tau_scale)), persistent=False)
        self.register_buffer("positional", periodic_encoding(torch.arange(self.period), d, self.period),
                             persistent=False)
        self.expression = ExpressionEncoder(cfg)
        # The motion encoder: previous tau (with feedback), then eta - 1 (with use_eta).
        inputs = int(self.feedback) + int(self.use_eta)
        self.motion = nn.Linear(inputs, d) if inputs else None  # (without: the style rows are the token bias)
        self.style = nn.Embedding(len(self.subjects) + 1, d)
        # Per-subject log gain of the output (people's larynx moves by different amounts for the same face:
        # a gain is a product, which the additive style of the tokens can only approximate); 0 = the average.
        self.style_gain = nn.Embedding(len(self.subjects) + 1, 1)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layers))
        self.ln_out = nn.LayerNorm(d) if cfg.output_norm else None
        self.head = nn.Linear(d, 1)
        nn.init.zeros_(self.style.weight)
        nn.init.zeros_(self.style_gain.weight)
        nn.init.normal_(self.head.weight, std=0.01)
        nn.init.zeros_(self.head.bias)

    @property
    def config(self) -> dict:
        """The checkpoint's ``model_config``: the sizes and the data fields (what :func:`build_model` takes)."""
        return {**dataclasses.asdict(self.cfg), **dataclasses.asdict(self.data)}

    # ------------------------------------------------------------------ helpers

    def subject_index(self, subject: str | None) -> int:
        """Style index of a subject name (0 for None = unknown subject)."""
        if subject is None:
            return 0
        if str(subject) not in self.subjects:
            known = ", ".join(self.subjects[:20]) + (" ..." if len(self.subjects) > 20 else "")
            raise InputError(f"subject '{subject}' was not in the training data (known: {known or 'none'}); "
                             f"leave subject unset for the average style")
        return self.subjects.index(str(subject)) + 1

    def shift(self, tau: Tensor) -> Tensor:
        """previous_tau for teacher forcing: [tau_mean, tau[0], ..., tau[T-2]] per row of tau [B,T]."""
        return torch.cat([self.tau_mean.expand(tau.shape[0], 1).to(tau.dtype), tau[:, :-1]], dim=1)

    def token_base(self, batch_size: int, subject: Tensor | None, eta: Tensor | None) -> Tensor:
        """The part of the tokens that depends neither on tau nor on psi: [B,period,d].

        A token is ``motion([previous normalised tau,] [eta - 1]) + positional(t mod period) + style
        + expression features(t)``; the motion encoder is linear, so everything but
        ``previous * motion.weight[:, 0]`` (with feedback) and the expression features is a table over
        the period.
        """
        base = (self.positional if self.motion is None else self.motion.bias + self.positional)[None]  # [1,period,d]
        style = self.style.weight[:1] if subject is None else self.style(subject)  # [1 or B,d]
        base = base + style[:, None, :]
        if self.use_eta:
            if eta is None:
                raise ValueError("this model takes eta (use_eta); pass eta [B]")
            base = base + (eta.to(base.dtype) - 1.0)[:, None, None] * self.motion.weight[:, int(self.feedback)]
        return base.expand(batch_size, -1, -1)

    def _tokens(self, previous_tau: Tensor, memory: Tensor, subject: Tensor | None, eta: Tensor | None) -> Tensor:
        """Decoder tokens [B,T,d] for previous_tau [B,T] (UV units) and expression features memory [B,T,d]."""
        base = self.token_base(memory.shape[0], subject, eta)
        positions = torch.arange(memory.shape[1], device=memory.device) % self.period
        tokens = base[:, positions] + memory
        if self.feedback:
            normalised = (previous_tau - self.tau_mean) / self.tau_scale
            tokens = tokens + normalised[..., None] * self.motion.weight[:, 0]
        return tokens

    def to_tau(self, normalised: Tensor) -> Tensor:
        """Normalised tau [...] (the network's output) -> tau [...] in UV units."""
        return self.tau_mean + self.tau_scale * normalised

    def output_gain(self, batch_size: int, subject: Tensor | None) -> Tensor:
        """The per-subject factor [B,1] of the normalised output (the unknown subject's for None)."""
        gain = self.style_gain.weight[:1] if subject is None else self.style_gain(subject)  # [1 or B,1]
        return torch.exp(gain).expand(batch_size, 1)

    def _readout(self, x: Tensor, subject: Tensor | None) -> Tensor:
        """Hidden states [B,T,d] -> tau [B,T] in UV units."""
        x = x if self.ln_out is None else self.ln_out(x)
        return self.to_tau(self.head(x)[..., 0] * self.output_gain(x.shape[0], subject))

    # ------------------------------------------------------------------ teacher forcing

    def forward(self, psi: Tensor, previous_tau: Tensor | None, subject: Tensor | None = None,
                eta: Tensor | None = None) -> Tensor:
        """Teacher-forced tau.

        Args:
            psi: [B,T,55] expression weights at ``fps``.
            previous_tau: [B,T] the tau fed to each frame, UV units (see :meth:`shift`); unused (may be
                None) without ``feedback``.
            subject: [B] long style indices (None: the unknown subject's style for all).
            eta: [B] larynx sizes (only with ``use_eta``).

        Returns:
            tau [B,T] in UV units; frame t depends on psi[:, :t+1] and previous_tau[:, :t+1] only.
        """
        memory, _ = self.expression(psi)
        x = self._tokens(previous_tau, memory, subject, eta)
        for block in self.blocks:
            x = block(x, memory)
        return self._readout(x, subject)

    # ------------------------------------------------------------------ decoding

    def stream(self, batch_size: int = 1, subject: Tensor | None = None, eta: Tensor | None = None) -> LarynxStream:
        """A frame-by-frame decoder (see :class:`LarynxStream`)."""
        return LarynxStream(self, batch_size, subject, eta)

    @torch.inference_mode()
    def generate(self, psi: Tensor, subject: Tensor | None = None, eta: Tensor | None = None,
                 chunk: int = 1024) -> Tensor:
        """Autoregressive tau [B,T] (UV units) from psi [B,T,55], streamed with the cache (any length).

        The expression side (encoder, cross-attention inputs) is computed ``chunk`` frames at a time,
        the autoregressive side frame by frame; memory is O(chunk + window) beyond input and output.
        """
        stream = self.stream(psi.shape[0], subject, eta)
        out = torch.empty(psi.shape[:2], dtype=psi.dtype, device=psi.device)
        for start in range(0, psi.shape[1], chunk):
            frames = stream.encode(psi[:, start:start + chunk])
            with single_thread():
                for t, frame in enumerate(frames):
                    out[:, start + t] = stream.advance(frame)
        return self.to_tau(out)

    @torch.no_grad()
    def generate_uncached(self, psi: Tensor, subject: Tensor | None = None, eta: Tensor | None = None) -> Tensor:
        """Reference decoding as FaceFormer does it: rerun ``forward`` on the whole prefix at every frame (O(T^2)).

        (Without ``feedback`` one ``forward`` pass gives the same; the prefix loop keeps this the reference
        of what the stream computes frame by frame.)"""
        previous = self.tau_mean.expand(psi.shape[0], 1).to(psi.dtype)
        out = []
        for t in range(psi.shape[1]):
            tau = self.forward(psi[:, : t + 1], previous, subject, eta)[:, -1]
            out.append(tau)
            previous = torch.cat([previous, tau[:, None]], dim=1)
        return torch.stack(out, dim=1)


def _affine(weight: Tensor, bias: Tensor, norm: nn.LayerNorm | None = None) -> tuple[Tensor, Tensor]:
    """``(bias, weight_t)`` of y = x W^T + b, computed as ``torch.addmm(bias, x, weight_t)``.

    With ``norm``, the LayerNorm before the product is folded in: W (g * n + beta) + b = (W g) n + (W beta + b)
    for the normalised n, so the norm runs without its affine part (:func:`_normalise`).
    """
    weight, bias = weight.detach(), bias.detach()
    if norm is not None:
        bias = bias + weight @ norm.bias.detach()
        weight = weight * norm.weight.detach()
    return bias, weight.t()


def _linear(layer: nn.Linear, norm: nn.LayerNorm | None = None) -> tuple[Tensor, Tensor]:
    """:func:`_affine` of a linear layer."""
    return _affine(layer.weight, layer.bias, norm)


def _normalise(x: Tensor, eps: float) -> Tensor:
    """LayerNorm without its affine part over the last dimension (folded into the next product, :func:`_affine`)."""
    return F.layer_norm(x, x.shape[-1:], None, None, eps)


class FrameWeights:
    """The weights of one live frame, taken from a model once per :class:`LarynxStream` and laid out for
    products with a single frame.

    A live frame is some hundred operations on 64-wide vectors, and each costs its call more than its
    arithmetic: calling a module, or reading a parameter through one, costs as much as a product.  So the
    stream holds plain tensors, in the layout of ``torch.addmm(bias, x, weight_t)`` (:func:`_affine`): each
    convolution kernel flattened in the order of its taps (oldest first), the one-frame cross-attention's
    value and output projections multiplied into one, every LayerNorm that precedes a product folded into
    it, the low-passes' decays evaluated.
    """

    def __init__(self, model: LarynxTransformer):
        encoder = model.expression
        with torch.no_grad():
            self.knots, self.project = encoder.knots, _linear(encoder.project)
            # Conv1d weight [C_out,C_in,kernel] -> [C_out, kernel*C_in], matching taps [B,kernel,C_in] flattened
            self.convs = [(conv.dilation, *_affine(conv.conv.weight.permute(0, 2, 1).flatten(1), conv.conv.bias))
                          for conv in encoder.temporal]
            r = encoder.recurrent
            self.recurrent = None if r is None else tuple(
                p.detach() for p in (r.weight_ih_l0, r.weight_hh_l0, r.bias_ih_l0, r.bias_hh_l0))
            smoothing = encoder.smoothing
            self.smoothing = None if smoothing is None else (smoothing.decay().detach(), _linear(smoothing.mix))
            norm = encoder.norm  # its output is the memory itself: not folded
            self.encoder_norm = norm.normalized_shape, norm.weight.detach(), norm.bias.detach(), norm.eps
            self.motion = model.motion.weight[:, 0].detach() if model.feedback else None
            self.blocks = [BlockFrameWeights(block) for block in model.blocks]
            self.out_eps = None if model.ln_out is None else model.ln_out.eps
            self.head = _linear(model.head, model.ln_out)


class BlockFrameWeights:
    """One decoder block's part of :class:`FrameWeights`."""

    def __init__(self, block: Block):
        cross, attention = block.cross, block.attention
        self.heads = attention.n_heads
        self.self_eps, self.qkv = block.ln_self.eps, _linear(attention.qkv, block.ln_self)
        self.self_out = _linear(attention.out)
        if cross.window == 1:  # out(kv(memory)) as one product
            self.cross_values = _affine(cross.out.weight @ cross.kv.weight,
                                        cross.out.weight @ cross.kv.bias + cross.out.bias)
            self.cross_eps = self.cross_query = None
        else:
            self.cross_values = _linear(cross.kv)
            self.cross_eps, self.cross_query = cross.norm.eps, _linear(cross.q, cross.norm)
        self.cross_out = _linear(cross.out)
        self.mlp_eps, self.mlp_in = block.ln_mlp.eps, _linear(block.mlp[0], block.ln_mlp)
        self.mlp_out = _linear(block.mlp[2])


@dataclass
class EncodedFrame:
    """One frame's expression side, computed ahead by :meth:`LarynxStream.encode`: its features [B,d]
    and per block the cross-attention input: the attention's output [B,d] with a one-frame window (it does
    not depend on the query), else the frame's keys and values [2,B,H,dh] (:meth:`CrossAttention.encode`)."""

    memory: Tensor
    cross: list[Tensor]


class LarynxStream:
    """Live decoding, one frame at a time, at constant cost per frame and bounded memory.

    ``step(psi_t [B,55]) -> tau_t [B]`` (UV units).  The stream keeps the expression encoder's
    state (:class:`EncoderState`: convolution history, recurrent state, smoothed values), per block a
    :class:`BlockState` (a self-attention :class:`WindowCache` of ``window`` frames, and a cross-attention
    one of ``cross_window`` frames), and the last prediction (fed back into the next token with
    ``feedback``).  Nothing in it grows with the position (:func:`tensor_bytes` measures it).

    The frames are computed from ``weights`` (:class:`FrameWeights`), a snapshot of the model's taken when
    the stream is made: make a new stream after training further.  Many frames given at once
    (:meth:`encode`, as :meth:`LarynxTransformer.generate` does) run the encoder's modules over all of them;
    the autoregressive side always runs frame by frame.
    """

    def __init__(self, model: LarynxTransformer, batch_size: int = 1, subject: Tensor | None = None,
                 eta: Tensor | None = None):
        self.model = model
        self.batch_size = batch_size
        cfg = model.cfg
        weight = next(model.parameters())
        dtype, device = weight.dtype, weight.device  # the stream lives where the model does
        heads, head_dim = cfg.n_heads, cfg.d_model // cfg.n_heads
        self.weights = FrameWeights(model)
        with torch.no_grad():
            self.token_base = model.token_base(batch_size, subject, eta).to(dtype)  # [B,period,d]
            self.gain = model.output_gain(batch_size, subject).to(dtype)  # [B,1]
        slopes = alibi_slopes(heads).to(device)
        self.blocks = []
        for _ in model.blocks:
            state = BlockState(WindowCache(batch_size, heads, head_dim, model.window, dtype, device),
                               step_bias(slopes, model.period, model.window, batch_size).to(dtype))
            if model.cross_window > 1:
                state.cross_cache = WindowCache(batch_size, heads, head_dim, model.cross_window, dtype, device)
                state.cross_bias = step_bias(slopes, 1, model.cross_window, batch_size).to(dtype)
            self.blocks.append(state)
        self.expression_state = model.expression.initial_state(batch_size, dtype)
        # normalised tau of the last frame (0 = tau_mean)
        self.previous = torch.zeros(batch_size, 1, dtype=dtype, device=device)
        self.position = 0

    def state_bytes(self) -> int:
        """Bytes of the tensors the stream carries from frame to frame: all it holds but its model and its
        snapshot of the weights (both fixed for the stream's life)."""
        return tensor_bytes(self, exclude=(self.model, self.weights))

    @torch.inference_mode()
    def encode(self, psi: Tensor) -> list[EncodedFrame]:
        """The expression side of frames psi [B,C,55] that continue the stream, one :class:`EncodedFrame`
        per frame (computed for all C frames at once, by the model's modules)."""
        model = self.model
        memory, self.expression_state = model.expression(psi, self.expression_state)
        cross = [block.cross.encode(memory) for block in model.blocks]
        return [EncodedFrame(m, [c[t] for c in cross]) for t, m in enumerate(memory.unbind(1))]

    @torch.inference_mode()
    def encode_frame(self, psi_t: Tensor) -> EncodedFrame:
        """The expression side of one frame psi_t [B,55] that continues the stream: what :meth:`encode` gives
        for a single frame, computed from :attr:`weights` (ExpressionEncoder.forward step by step)."""
        weights, state = self.weights, self.expression_state
        x = torch.addmm(weights.project[0], hinge_features(psi_t, weights.knots), weights.project[1])
        conv_history = []
        for (dilation, bias, kernel), history in zip(weights.convs, state.conv):
            joined = torch.cat([history, x[:, None]], dim=1)  # [B,history+1,d]
            conv_history.append(joined[:, 1:])
            x = x + F.gelu(torch.addmm(bias, joined[:, ::dilation].flatten(1), kernel), approximate="tanh")
        hidden = state.recurrent
        if weights.recurrent is not None:
            before = x.new_zeros(x.shape) if hidden is None else hidden[0]
            hidden = torch.gru_cell(x, before, *weights.recurrent)
            x = x + hidden
            hidden = hidden[None]
        smooth = state.smooth
        if weights.smoothing is not None:
            decay, mix = weights.smoothing
            smooth = x if smooth is None else torch.lerp(x, smooth, decay)
            x = x + torch.addmm(mix[0], smooth, mix[1])
        self.expression_state = EncoderState(conv_history, smooth, hidden)
        memory = F.layer_norm(x, *weights.encoder_norm)
        cross = []
        for block in weights.blocks:
            encoded = torch.addmm(block.cross_values[0], memory, block.cross_values[1])
            if block.cross_query is not None:  # keys and values [2,B,H,dh]
                encoded = encoded.view(x.shape[0], 2, block.heads, -1).transpose(0, 1)
            cross.append(encoded)
        return EncodedFrame(memory, cross)

    @torch.inference_mode()
    def advance(self, frame: EncodedFrame) -> Tensor:
        """Decode the next frame from its encoded expressions (:meth:`encode`, :meth:`encode_frame`): the
        decoder blocks' ``forward`` for one frame, from :attr:`weights` and the caches.

        Returns the normalised prediction [B] ((tau - tau_mean) / tau_scale).
        """
        weights, batch = self.weights, self.batch_size
        x = self.token_base[:, self.position % self.model.period] + frame.memory
        if weights.motion is not None:
            x = torch.addcmul(x, self.previous, weights.motion)
        for block, cross, state in zip(weights.blocks, frame.cross, self.blocks):
            qkv = torch.addmm(block.qkv[0], _normalise(x, block.self_eps), block.qkv[1])
            qkv = qkv.view(batch, 3, block.heads, -1)
            keys, values = state.self_cache.append(qkv[:, 1:].transpose(0, 1))
            attended = attend_one(qkv[:, 0], keys, values, state.self_bias[:, -keys.shape[2]:])
            x = x + torch.addmm(block.self_out[0], attended, block.self_out[1])
            if block.cross_query is None:
                x = x + cross
            else:
                q = torch.addmm(block.cross_query[0], _normalise(x, block.cross_eps), block.cross_query[1])
                keys, values = state.cross_cache.append(cross)
                attended = attend_one(q.view(batch, block.heads, -1), keys, values,
                                      state.cross_bias[:, -keys.shape[2]:])
                x = x + torch.addmm(block.cross_out[0], attended, block.cross_out[1])
            hidden = F.gelu(torch.addmm(block.mlp_in[0], _normalise(x, block.mlp_eps), block.mlp_in[1]),
                            approximate="tanh")
            x = x + torch.addmm(block.mlp_out[0], hidden, block.mlp_out[1])
        x = x if weights.out_eps is None else _normalise(x, weights.out_eps)
        y = torch.addmm(weights.head[0], x, weights.head[1]) * self.gain  # [B,1]
        self.previous = y
        self.position += 1
        return y[:, 0]

    @torch.inference_mode()
    def step(self, psi_t: Tensor) -> Tensor:
        """One live frame: psi_t [B,55] (or [55] for B = 1) -> tau_t [B] (UV units)."""
        psi_t = torch.as_tensor(psi_t, dtype=self.previous.dtype, device=self.previous.device)
        psi_t = psi_t.reshape(self.batch_size, NUM_EXPRESSIONS)
        with single_thread():
            y = self.advance(self.encode_frame(psi_t))
        return self.model.to_tau(y)


def tensor_bytes(root, exclude: tuple = ()) -> int:
    """Bytes of the storage of every tensor reachable from ``root`` through attributes, lists, tuples, dicts
    and dataclasses, each storage counted once (views share it); objects in ``exclude`` (e.g. the model,
    whose weights do not belong to a stream) are not entered."""
    seen_storages, seen_objects, total = set(), set(), 0
    skip = {id(x) for x in exclude}
    pending = [root]
    while pending:
        obj = pending.pop()
        if id(obj) in seen_objects or id(obj) in skip:
            continue
        seen_objects.add(id(obj))
        if isinstance(obj, Tensor):
            storage = obj.untyped_storage()
            if storage.data_ptr() not in seen_storages:
                seen_storages.add(storage.data_ptr())
                total += storage.nbytes()
        elif isinstance(obj, dict):
            pending.extend(obj.values())
        elif isinstance(obj, (list, tuple, set)):
            pending.extend(obj)
        elif hasattr(obj, "__dict__") and not isinstance(obj, type):
            pending.extend(vars(obj).values())
    return total


# The sizes of checkpoints saved before these options existed: no hinges, and a LayerNorm before the head.
SIZES_BEFORE_OPTIONS = {"input_knots": [], "output_norm": True}


def build_model(model_config: dict) -> LarynxTransformer:
    """The model of a checkpoint's ``model_config``: exactly the fields of :class:`LarynxTransformerConfig`
    (the sizes) and of :class:`LarynxDataFields` (from the training data); missing or unknown keys, or
    sizes the config rejects, are a ValueError."""
    model_config = {**SIZES_BEFORE_OPTIONS, **model_config}
    missing = [k for k in SIZES + DATA_KEYS if k not in model_config]
    unknown = sorted(set(model_config) - set(SIZES) - set(DATA_KEYS))
    if missing or unknown:
        raise ValueError(f"larynx transformer config: missing {missing}, unknown {unknown}; expected the sizes "
                         f"{list(SIZES)} (LarynxTransformerConfig) and the data's {list(DATA_KEYS)}")
    sizes = {k: model_config[k] for k in SIZES}
    sizes["expression_dilations"] = [int(d) for d in sizes["expression_dilations"]]
    sizes["input_knots"] = [float(k) for k in sizes["input_knots"]]
    data = {k: model_config[k] for k in DATA_KEYS}
    return LarynxTransformer(LarynxTransformerConfig(**sizes),
                             LarynxDataFields(float(data["fps"]), [str(s) for s in data["subjects"]],
                                              float(data["tau_mean"]), float(data["tau_scale"])))


# The per-subject tables: one row per training subject after row 0, the average person.
STYLE_TABLES = ("style.weight", "style_gain.weight")


def transfer_weights(model: LarynxTransformer, source: dict[str, Tensor]) -> None:
    """Start ``model`` from another run's weights ``source`` (a state dict of the same sizes).

    Every tensor is copied except the per-subject tables (:data:`STYLE_TABLES`), whose subjects differ
    between data sets: there each of ``model``'s rows, the average person's included, starts from the
    source's average person (row 0).  The tau normalisation is not in the weights: the head predicts
    normalised tau, and ``model`` keeps its own data's ``tau_mean`` and ``tau_scale``.

    Raises:
        ValueError: a tensor missing from ``source``, one ``model`` has not, or one of another shape (other
        sizes), naming it.
    """
    target = model.state_dict()
    missing = [k for k in target if k not in source]
    extra = [k for k in source if k not in target]  # a module the model has not (a LayerNorm before the head)
    other = [f"{k} {tuple(source[k].shape)} (expected {tuple(v.shape)})" for k, v in target.items()
             if k in source and k not in STYLE_TABLES and source[k].shape != v.shape]
    problems = [f"{what} {', '.join(names)}" for what, names in
                (("missing", missing), ("not in this model", extra), ("other sizes:", other)) if names]
    if problems:
        raise ValueError("the weights are of another model layout: " + "; ".join(problems))
    merged = {k: source[k].to(v.dtype) for k, v in target.items()}
    for name in STYLE_TABLES:
        merged[name] = source[name][:1].to(target[name].dtype).expand_as(target[name]).clone()
    model.load_state_dict(merged)


def predict_tau(model: LarynxTransformer, psi: np.ndarray, subject: str | None = None,
                eta: float | None = None) -> np.ndarray:
    """The larynx slide of one recording, streamed (as live decoding would produce it).

    Args:
        model: a trained model.
        psi: [T,55] expression weights at ``model.fps``, ``EXPRESSION_NAMES`` order.
        subject: a training subject's name for their style, or None for the average style.
        eta: the larynx size, for models with ``use_eta`` (default 1).

    Returns:
        tau [T] float64, UV units of the larynx map, + = up the neck.

    Raises:
        InputError: psi not [T,55], or ``subject`` not among the training subjects.
    """
    psi = np.asarray(psi, dtype=np.float32)
    if psi.ndim != 2 or psi.shape[1] != NUM_EXPRESSIONS:
        raise InputError(f"psi of shape {psi.shape}, expected [T,{NUM_EXPRESSIONS}] expression weights")
    device = next(model.parameters()).device
    index = torch.tensor([model.subject_index(subject)], device=device)
    eta_t = torch.tensor([1.0 if eta is None else float(eta)], device=device) if model.use_eta else None
    model.eval()
    tau = model.generate(torch.from_numpy(psi)[None].to(device), index, eta_t)[0]
    return tau.cpu().numpy().astype(np.float64)
