"""Expression -> larynx transformer (FaceFormer-style) with a streaming decoder of bounded cost.

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

Conventions (shapes carry a batch B and frames T):
- psi [B,T,55]: expression weights in ``data.expressions.EXPRESSION_NAMES`` order, at
  ``model.fps`` frames per second (the rate of the training data);
- tau [B,T]: larynx slide in UV units of the larynx map, + = up the neck (``data.synthetic_tau``).
  Inside the network tau is normalised, ``(tau - tau_mean) / tau_scale`` (both in the config);
- ``previous_tau`` [B,T]: the tau fed to frame t, i.e. tau of frame t-1 (``tau_mean`` at t = 0),
  see :meth:`LarynxTransformer.shift`;
- frame t's prediction depends on psi[:, :t+1] and previous_tau[:, :t+1] only (causal);
- subject [B] long: index into the style table, 0 = unknown subject (average style); names are
  ``model_config["subjects"]`` (index i+1 is ``subjects[i]``);
- eta [B]: larynx size, an input only when ``use_eta`` (1 = template size).
"""
from __future__ import annotations

import contextlib
import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from data.expressions import NUM_EXPRESSIONS
from data.errors import InputError

# Sizes come from configs/model/larynx_transformer.yaml (their one home, documented there).
SIZES = ("d_model", "n_heads", "n_layers", "d_ff", "window", "cross_window", "period", "expression_layers",
         "expression_kernel", "dropout", "use_eta")
# From the training data, filled in by the task: the frame rate of psi and tau (frames per second), the
# training subject names (style index i+1 is subjects[i], 0 the unknown subject), the tau normalisation
# (UV units).
DATA_KEYS = ("fps", "subjects", "tau_mean", "tau_scale")


@contextlib.contextmanager
def single_thread():
    """Run torch ops on one thread inside the block (restoring the setting after).

    Per-frame decoding works on tensors of a few hundred numbers: intra-op parallelism cannot speed
    them up, it only adds synchronisation, which stalls for milliseconds when another process holds
    the other core.
    """
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


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
        offsets = torch.arange(start, stop)[:, None] - torch.arange(first, stop)[None, :]
        bias = relative_bias(offsets, slopes, period, window).to(q.dtype)  # [H,chunk,keys]
        scores = torch.matmul(q[:, :, start:stop], k[:, :, first:stop].transpose(-1, -2)) * q.shape[-1] ** -0.5
        out.append(torch.matmul(torch.softmax(scores + bias, dim=-1), v[:, :, first:stop]))
    return torch.cat(out, dim=2)


class CausalConv(nn.Module):
    """Temporal convolution over past frames only: y[t] = sum_j W_j x[t-kernel+1+j] (zeros before frame 0)."""

    def __init__(self, channels: int, kernel: int):
        super().__init__()
        self.kernel = kernel
        self.conv = nn.Conv1d(channels, channels, kernel)

    def forward(self, x: Tensor, history: Tensor | None = None) -> Tensor:
        """x [B,T,C], history [B,kernel-1,C] (the frames before x; zeros if None) -> [B,T,C]."""
        if history is None:
            history = x.new_zeros(x.shape[0], self.kernel - 1, x.shape[2])
        return self.conv(torch.cat([history, x], dim=1).transpose(1, 2)).transpose(1, 2)


class ExpressionEncoder(nn.Module):
    """psi [B,T,55] -> features [B,T,d]: a linear projection, then residual causal convolutions."""

    def __init__(self, d_model: int, layers: int, kernel: int):
        super().__init__()
        self.project = nn.Linear(NUM_EXPRESSIONS, d_model)
        self.temporal = nn.ModuleList(CausalConv(d_model, kernel) for _ in range(layers))

    def forward(self, psi: Tensor, history: list[Tensor] | None = None) -> tuple[Tensor, list[Tensor]]:
        """Encode frames after ``history`` (per layer, the last kernel-1 inputs); returns (features, new history)."""
        x = self.project(psi)
        new_history = []
        for i, conv in enumerate(self.temporal):
            past = None if history is None else history[i]
            joined = x if past is None else torch.cat([past, x], dim=1)
            new_history.append(_tail(joined, conv.kernel - 1))
            x = x + F.gelu(conv(x, past), approximate="tanh")
        return x, new_history


def _tail(x: Tensor, count: int) -> Tensor:
    """The last ``count`` frames of x [B,T,C], zero-padded in front when T < count."""
    if x.shape[1] >= count:
        return x[:, x.shape[1] - count:]
    return torch.cat([x.new_zeros(x.shape[0], count - x.shape[1], x.shape[2]), x], dim=1)


class Block(nn.Module):
    """Pre-norm decoder block: periodic-biased causal self-attention, aligned cross-attention, MLP."""

    def __init__(self, cfg: dict):
        super().__init__()
        d, self.n_heads = cfg["d_model"], cfg["n_heads"]
        self.window, self.cross_window, self.period = int(cfg["window"]), int(cfg["cross_window"]), int(cfg["period"])
        self.register_buffer("slopes", alibi_slopes(self.n_heads), persistent=False)
        self.ln_self, self.ln_mlp = nn.LayerNorm(d), nn.LayerNorm(d)
        self.qkv = nn.Linear(d, 3 * d)
        self.self_out = nn.Linear(d, d)
        # With a one-frame cross window the only key is the aligned frame: attention returns its value, so
        # neither a query nor keys are needed and cross_kv projects values only.
        self.ln_cross = nn.LayerNorm(d) if self.cross_window > 1 else None
        self.cross_q = nn.Linear(d, d) if self.cross_window > 1 else None
        self.cross_kv = nn.Linear(d, (2 if self.cross_window > 1 else 1) * d)
        self.cross_out = nn.Linear(d, d)
        self.mlp = nn.Sequential(nn.Linear(d, cfg["d_ff"]), nn.GELU(approximate="tanh"), nn.Linear(cfg["d_ff"], d))
        self.dropout = nn.Dropout(cfg["dropout"])

    def heads(self, x: Tensor) -> Tensor:
        """[B,T,d] -> [B,H,T,d/H]."""
        return x.view(x.shape[0], x.shape[1], self.n_heads, -1).transpose(1, 2)

    def merge(self, x: Tensor) -> Tensor:
        """[B,H,T,d/H] -> [B,T,d]."""
        return x.transpose(1, 2).reshape(x.shape[0], x.shape[2], -1)

    def forward(self, x: Tensor, memory: Tensor) -> Tensor:
        """x [B,T,d] tokens, memory [B,T,d] encoded expressions -> [B,T,d]."""
        q, k, v = map(self.heads, self.qkv(self.ln_self(x)).chunk(3, dim=-1))
        a = banded_attention(q, k, v, self.slopes, self.period, self.window)
        x = x + self.dropout(self.self_out(self.merge(a)))
        if self.cross_window == 1:
            a = self.cross_kv(memory)  # attention over a single key returns its value
        else:
            q = self.heads(self.cross_q(self.ln_cross(x)))
            k, v = map(self.heads, self.cross_kv(memory).chunk(2, dim=-1))
            a = self.merge(banded_attention(q, k, v, self.slopes, 1, self.cross_window))  # bias: -slope * offset
        x = x + self.dropout(self.cross_out(a))
        return x + self.dropout(self.mlp(self.ln_mlp(x)))


class LarynxTransformer(nn.Module):
    """tau from psi: autoregressive over tau, cross-attending to the expressions (see module docstring)."""

    def __init__(self, cfg: dict):
        super().__init__()
        self.config = dict(cfg)
        d = cfg["d_model"]
        if d % cfg["n_heads"] or (d // cfg["n_heads"]) % 2:
            raise ValueError(f"d_model {d} must split into {cfg['n_heads']} heads of even size")
        self.fps = float(cfg["fps"])
        self.window, self.cross_window, self.period = int(cfg["window"]), int(cfg["cross_window"]), int(cfg["period"])
        self.subjects = [str(s) for s in cfg["subjects"]]
        self.use_eta = bool(cfg["use_eta"])
        self.register_buffer("tau_mean", torch.tensor(float(cfg["tau_mean"])), persistent=False)
        self.register_buffer("tau_scale", torch.tensor(float(cfg["tau_scale"])), persistent=False)
        self.register_buffer("positional", periodic_encoding(torch.arange(self.period), d, self.period), persistent=False)
        self.expression = ExpressionEncoder(d, cfg["expression_layers"], cfg["expression_kernel"])
        self.motion = nn.Linear(2 if self.use_eta else 1, d)
        self.style = nn.Embedding(len(self.subjects) + 1, d)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg["n_layers"]))
        self.ln_out = nn.LayerNorm(d)
        self.head = nn.Linear(d, 1)
        nn.init.zeros_(self.style.weight)
        nn.init.normal_(self.head.weight, std=0.01)
        nn.init.zeros_(self.head.bias)

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
        """The part of the motion tokens that does not depend on tau: [B,period,d].

        A token is ``motion(previous normalised tau [, eta - 1]) + positional(t mod period) + style``;
        the motion encoder is linear, so everything but ``previous * motion.weight[:, 0]`` is a table
        over the period.
        """
        base = (self.motion.bias + self.positional)[None]  # [1,period,d]
        style = self.style.weight[:1] if subject is None else self.style(subject)  # [1 or B,d]
        base = base + style[:, None, :]
        if self.use_eta:
            if eta is None:
                raise ValueError("this model takes eta (use_eta); pass eta [B]")
            base = base + (eta.to(base.dtype) - 1.0)[:, None, None] * self.motion.weight[:, 1]
        return base.expand(batch_size, -1, -1)

    def _tokens(self, previous_tau: Tensor, subject: Tensor | None, eta: Tensor | None) -> Tensor:
        """Motion tokens [B,T,d] for previous_tau [B,T] (UV units) at frames 0..T-1."""
        base = self.token_base(previous_tau.shape[0], subject, eta)
        positions = torch.arange(previous_tau.shape[1]) % self.period
        normalised = (previous_tau - self.tau_mean) / self.tau_scale
        return base[:, positions] + normalised[..., None] * self.motion.weight[:, 0]

    def to_tau(self, normalised: Tensor) -> Tensor:
        """Normalised tau [...] (the network's output) -> tau [...] in UV units."""
        return self.tau_mean + self.tau_scale * normalised

    def _readout(self, x: Tensor) -> Tensor:
        """Hidden states [...,d] -> tau [...] in UV units."""
        return self.to_tau(self.head(self.ln_out(x))[..., 0])

    # ------------------------------------------------------------------ teacher forcing

    def forward(self, psi: Tensor, previous_tau: Tensor, subject: Tensor | None = None,
                eta: Tensor | None = None) -> Tensor:
        """Teacher-forced tau [B,T] (UV units) from psi [B,T,55] and previous_tau [B,T] (see ``shift``)."""
        memory, _ = self.expression(psi)
        x = self._tokens(previous_tau, subject, eta)
        for block in self.blocks:
            x = block(x, memory)
        return self._readout(x)

    # ------------------------------------------------------------------ decoding

    def stream(self, batch_size: int = 1, subject: Tensor | None = None, eta: Tensor | None = None) -> "LarynxStream":
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
        out = torch.empty(psi.shape[:2], dtype=psi.dtype)
        for start in range(0, psi.shape[1], chunk):
            cross = stream.encode(psi[:, start:start + chunk])
            with single_thread():
                for t in range(len(cross[0])):
                    out[:, start + t] = stream.advance([frames[t] for frames in cross])
        return self.to_tau(out)

    @torch.no_grad()
    def generate_uncached(self, psi: Tensor, subject: Tensor | None = None, eta: Tensor | None = None) -> Tensor:
        """Reference decoding as FaceFormer does it: rerun ``forward`` on the whole prefix at every frame (O(T^2))."""
        previous = self.tau_mean.expand(psi.shape[0], 1).to(psi.dtype)
        out = []
        for t in range(psi.shape[1]):
            tau = self.forward(psi[:, : t + 1], previous, subject, eta)[:, -1]
            out.append(tau)
            previous = torch.cat([previous, tau[:, None]], dim=1)
        return torch.stack(out, dim=1)


class WindowCache:
    """Keys and values of the last ``window`` frames, as [B,H,n,dh] views in frame order.

    Each frame is written twice, at slot ``t % window`` and ``t % window + window`` of a buffer of
    2 * window slots, so the last n frames are always the contiguous slice ending at slot
    ``t % window + window``: no copying or rolling, and memory fixed at 2 * window frames.
    """

    def __init__(self, batch: int, heads: int, head_dim: int, window: int, dtype=torch.float32):
        self.window = window
        self.kv = torch.zeros(2, batch, heads, 2 * window, head_dim, dtype=dtype)  # keys, values
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


class LarynxStream:
    """Live decoding, one frame at a time, at constant cost per frame and bounded memory.

    ``step(psi_t [B,55]) -> tau_t [B]`` (UV units).  The stream keeps the expression encoder's
    convolution history, per block a self-attention :class:`WindowCache` of ``window`` frames (and a
    cross-attention one of ``cross_window`` frames), and the last prediction, fed back as the next
    frame's motion token.  Nothing in it grows with the position.
    """

    def __init__(self, model: LarynxTransformer, batch_size: int = 1, subject: Tensor | None = None,
                 eta: Tensor | None = None):
        self.model = model
        self.batch_size = batch_size
        cfg = model.config
        dtype = next(model.parameters()).dtype
        heads, head_dim = cfg["n_heads"], cfg["d_model"] // cfg["n_heads"]
        with torch.no_grad():  # a snapshot of the weights: make a new stream after training further
            self.token_base = model.token_base(batch_size, subject, eta).to(dtype)  # [B,period,d]
        self.self_caches = [WindowCache(batch_size, heads, head_dim, model.window, dtype) for _ in model.blocks]
        self.cross_caches = [WindowCache(batch_size, heads, head_dim, model.cross_window, dtype)
                             for _ in model.blocks] if model.cross_window > 1 else []
        self.conv_history = [torch.zeros(batch_size, cfg["expression_kernel"] - 1, cfg["d_model"], dtype=dtype)
                             for _ in model.expression.temporal]
        self.previous = torch.zeros(batch_size, 1, dtype=dtype)  # normalised tau of the last frame (0 = tau_mean)
        self.position = 0
        # Attention biases [B*H,window,1] (see attend_one) for offsets window-1, ..., 0: the last n keys
        # (oldest first) take the tail.
        slopes = model.blocks[0].slopes  # the same in every block
        offsets = torch.arange(model.window - 1, -1, -1)[None, :]
        bias = relative_bias(offsets, slopes, model.period, model.window)[:, 0]
        self.self_bias = bias.repeat(batch_size, 1)[:, :, None].to(dtype)
        offsets = torch.arange(model.cross_window - 1, -1, -1)[None, :]
        bias = relative_bias(offsets, slopes, 1, model.cross_window)[:, 0]
        self.cross_bias = bias.repeat(batch_size, 1)[:, :, None].to(dtype)

    def cache_elements(self) -> int:
        """Number of values the stream holds (constant: it does not grow with the position)."""
        tensors = [c.kv for c in self.self_caches + self.cross_caches] + self.conv_history + [self.previous]
        return sum(t.numel() for t in tensors)

    @torch.inference_mode()
    def encode(self, psi: Tensor) -> list[list[Tensor]]:
        """The cross-attention inputs of expression frames psi [B,C,55] that continue the stream.

        Returns per block a list of C frames: with ``cross_window`` 1 the attention has a single key
        (the aligned frame), so its output, [B,d], is computed here for all C frames at once;
        otherwise the frame's keys and values [2,B,H,dh] for the cross cache.
        """
        model = self.model
        memory, self.conv_history = model.expression(psi, self.conv_history)
        out = []
        for block in model.blocks:
            if model.cross_window == 1:
                out.append(list(block.cross_out(block.cross_kv(memory)).unbind(1)))  # values are the output
            else:
                k, v = map(block.heads, block.cross_kv(memory).chunk(2, dim=-1))  # [B,H,C,dh]
                out.append(list(torch.stack([k, v]).unbind(3)))
        return out

    @torch.inference_mode()
    def advance(self, cross: list[Tensor]) -> Tensor:
        """Decode the next frame from its cross-attention inputs (one per block, see ``encode``).

        Returns the normalised prediction [B] ((tau - tau_mean) / tau_scale).
        """
        model = self.model
        x = torch.addcmul(self.token_base[:, self.position % model.period], self.previous, model.motion.weight[:, 0])
        n_self = min(self.position + 1, model.window)
        n_cross = min(self.position + 1, model.cross_window)
        for i, block in enumerate(model.blocks):
            qkv = block.qkv(block.ln_self(x)).view(self.batch_size, 3, block.n_heads, -1)  # [B,3,H,dh]
            keys, values = self.self_caches[i].append(qkv[:, 1:].transpose(0, 1))
            x = x + block.self_out(attend_one(qkv[:, 0], keys, values, self.self_bias[:, -n_self:]))
            if model.cross_window == 1:
                x = x + cross[i]
            else:
                q = block.cross_q(block.ln_cross(x)).view(self.batch_size, block.n_heads, -1)
                keys, values = self.cross_caches[i].append(cross[i])
                x = x + block.cross_out(attend_one(q, keys, values, self.cross_bias[:, -n_cross:]))
            x = x + block.mlp(block.ln_mlp(x))
        y = model.head(model.ln_out(x))  # [B,1]
        self.previous = y
        self.position += 1
        return y[:, 0]

    @torch.inference_mode()
    def step(self, psi_t: Tensor) -> Tensor:
        """One live frame: psi_t [B,55] (or [55] for B = 1) -> tau_t [B] (UV units)."""
        psi_t = torch.as_tensor(psi_t, dtype=self.previous.dtype).reshape(self.batch_size, 1, NUM_EXPRESSIONS)
        with single_thread():
            y = self.advance([frames[0] for frames in self.encode(psi_t)])
        return self.model.to_tau(y)


def build_model(model_config: dict) -> LarynxTransformer:
    """The model for a config: exactly the keys of ``SIZES`` (configs/model/larynx_transformer.yaml) and
    ``DATA_KEYS`` (from the training data); missing or unknown keys are an error."""
    missing = [k for k in SIZES + DATA_KEYS if k not in model_config]
    unknown = sorted(set(model_config) - set(SIZES) - set(DATA_KEYS))
    if missing or unknown:
        raise ValueError(f"larynx transformer config: missing {missing}, unknown {unknown}; expected the sizes "
                         f"{list(SIZES)} (configs/model/larynx_transformer.yaml) and the data's {list(DATA_KEYS)}")
    return LarynxTransformer(model_config)


def predict_tau(model: LarynxTransformer, psi: np.ndarray, subject: str | None = None,
                eta: float | None = None) -> np.ndarray:
    """tau [T] (UV units) for one recording psi [T,55] at ``model.fps``; ``subject`` a training subject name."""
    psi = np.asarray(psi, dtype=np.float32)
    if psi.ndim != 2 or psi.shape[1] != NUM_EXPRESSIONS:
        raise InputError(f"psi of shape {psi.shape}, expected [T,{NUM_EXPRESSIONS}] expression weights")
    index = torch.tensor([model.subject_index(subject)])
    eta_t = torch.tensor([1.0 if eta is None else float(eta)]) if model.use_eta else None
    model.eval()
    return model.generate(torch.from_numpy(psi)[None], index, eta_t)[0].numpy().astype(np.float64)
