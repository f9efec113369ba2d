"""The larynx transformer's expression encoder: dilated causal convolutions, a GRU, learnt low-passes, a norm.

Every part is causal and carries its state across calls (:class:`EncoderState`), so a sequence encoded in
pieces gives the features of the whole; :func:`encoder_frame` is ``ExpressionEncoder.forward`` for one frame
(in eval mode), from a snapshot of its weights (:class:`EncoderFrameWeights`).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from data.expressions import NUM_EXPRESSIONS

from .config import LarynxTransformerConfig
from .folding import affine, linear, normalise, stacked


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
    (None before the first frame).  A stream's is stacked over the members (:func:`stack_states`)."""

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
        self.project = nn.Linear(NUM_EXPRESSIONS, d)
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
        x = self.project(psi)
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


class EncoderFrameWeights:
    """The members' :class:`ExpressionEncoder` weights for :func:`encoder_frame`, stacked (:mod:`.folding`): each
    convolution kernel flattened in the order of its taps (oldest first), the GRU's products, the low-passes'
    decays evaluated."""

    def __init__(self, encoders: list[ExpressionEncoder]):
        first = encoders[0]
        with torch.no_grad():
            self.project = stacked([linear(e.project) for e in encoders])
            # Conv1d weight [C_out,C_in,kernel] -> [C_out, kernel*C_in], matching taps [K,B,kernel,C_in] flattened
            self.convs = [(conv.dilation, *stacked([affine(c.conv.weight.permute(0, 2, 1).flatten(1), c.conv.bias)
                                                    for c in convs]))
                          for conv, convs in zip(first.temporal, zip(*(e.temporal for e in encoders)))]
            self.recurrent = None if first.recurrent is None else (
                stacked([affine(e.recurrent.weight_ih_l0, e.recurrent.bias_ih_l0) for e in encoders]),
                stacked([affine(e.recurrent.weight_hh_l0, e.recurrent.bias_hh_l0) for e in encoders]))
            self.smoothing = None if first.smoothing is None else (
                torch.stack([e.smoothing.decay().detach() for e in encoders])[:, None],
                stacked([linear(e.smoothing.mix) for e in encoders]))
            # The norm's output is the features themselves: its affine part is applied, not folded.
            self.norm = first.norm.eps
            self.norm_affine = (torch.stack([e.norm.bias.detach() for e in encoders])[:, None],    # [K,1,d]
                                torch.stack([e.norm.weight.detach() for e in encoders])[:, None])


def gru_frame(weights: tuple[tuple[Tensor, Tensor], tuple[Tensor, Tensor]], x: Tensor, hidden: Tensor) -> Tensor:
    """``torch.gru_cell`` for stacked members: x, hidden [K,B,d] -> the next hidden [K,B,d] (PyTorch's GRU:
    r, z = sigmoid(.), n = tanh(W_in x + b_in + r (W_hn h + b_hn)), h' = (1 - z) n + z h)."""
    (bias_i, weight_i), (bias_h, weight_h) = weights
    gates_x = torch.baddbmm(bias_i, x, weight_i)       # [K,B,3d]: r, z, n
    gates_h = torch.baddbmm(bias_h, hidden, weight_h)
    d = x.shape[-1]
    reset_update = torch.sigmoid(gates_x[..., :2 * d] + gates_h[..., :2 * d])
    candidate = torch.tanh(torch.addcmul(gates_x[..., 2 * d:], reset_update[..., :d], gates_h[..., 2 * d:]))
    return torch.lerp(candidate, hidden, reset_update[..., d:])


def encoder_frame(weights: EncoderFrameWeights, state: EncoderState, psi_t: Tensor) -> tuple[Tensor, EncoderState]:
    """``ExpressionEncoder.forward`` (eval mode) of every member for the one frame psi_t [B,55] after the stacked
    ``state`` (:func:`stack_states`): (features [K,B,d], the state after it)."""
    project_bias, project = weights.project
    x = torch.baddbmm(project_bias, psi_t.expand(project.shape[0], -1, -1), project)  # [K,B,d]
    conv_history = []
    for (dilation, bias, kernel), history in zip(weights.convs, state.conv):
        joined = torch.cat([history, x[:, :, None]], dim=2)  # [K,B,history+1,d]
        conv_history.append(joined[:, :, 1:])
        x = x + F.gelu(torch.baddbmm(bias, joined[:, :, ::dilation].flatten(2), kernel), approximate="tanh")
    hidden = state.recurrent
    if weights.recurrent is not None:
        hidden = gru_frame(weights.recurrent, x, torch.zeros_like(x) if hidden is None else hidden)
        x = x + hidden
    smooth = state.smooth
    if weights.smoothing is not None:
        decay, (mix_bias, mix) = weights.smoothing
        smooth = x if smooth is None else torch.lerp(x, smooth, decay)
        x = x + torch.baddbmm(mix_bias, smooth, mix)
    norm_bias, norm_weight = weights.norm_affine
    features = torch.addcmul(norm_bias, normalise(x, weights.norm), norm_weight)
    return features, EncoderState(conv_history, smooth, hidden)


def stack_states(states: list[EncoderState]) -> EncoderState:
    """The members' :class:`EncoderState` (as their modules carry it) -> one stacked state: convolution histories
    [K,B,history,d], the recurrent state [K,B,d], the smoothed value [K,B,d] (:func:`encoder_frame`'s)."""
    first = states[0]
    return EncoderState([torch.stack(history) for history in zip(*(s.conv for s in states))],
                        None if first.smooth is None else torch.stack([s.smooth for s in states]),
                        None if first.recurrent is None else torch.cat([s.recurrent for s in states]))


def member_state(state: EncoderState, member: int) -> EncoderState:
    """Member ``member``'s :class:`EncoderState` of a stacked one (:func:`stack_states`), as its module carries it."""
    return EncoderState([history[member] for history in state.conv],
                        None if state.smooth is None else state.smooth[member],
                        None if state.recurrent is None else state.recurrent[member:member + 1])
