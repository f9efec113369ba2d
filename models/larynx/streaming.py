"""Live decoding of the larynx transformer or of an ensemble of them: one frame at a time, at constant cost per
frame and bounded memory.

:class:`LarynxStream` runs the model's ``forward`` frame by frame through the per-frame version of each module,
written beside it: :func:`~models.larynx.encoder.encoder_frame` (the expression encoder from its carried state),
:func:`~models.larynx.block.cross_frame` and :func:`~models.larynx.block.block_frame` (each block's
self-attention over a cache of ``window`` frames).  They compute from a snapshot of the weights laid out for
single-frame products (:class:`FrameWeights`, :mod:`.folding`).

A member is a :class:`~models.larynx.model.LarynxTransformer` (this module reads its ``expression``, ``blocks``,
``head``, ``tau_mean``, ``tau_scale``, ``window``, ``cfg``, ``token_base`` and ``output_gain``); the model
imports this module for its ``stream``, so the members are typed as the ``nn.Module`` they are.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from base.threads import single_thread
from data.expressions import NUM_EXPRESSIONS

from .block import BlockFrameWeights, BlockState, block_frame, cross_frame
from .encoder import EncoderFrameWeights, encoder_frame, member_state, stack_states
from .folding import linear, stacked


class FrameWeights:
    """The weights of one live frame of every member, taken from the models once per :class:`LarynxStream` and
    stacked (:mod:`.folding`): the encoder's (:class:`EncoderFrameWeights`), each block's
    (:class:`BlockFrameWeights`), the head's, and each member's tau normalisation [K,1]."""

    def __init__(self, members: list[nn.Module]):
        self.encoder = EncoderFrameWeights([m.expression for m in members])
        self.blocks = [BlockFrameWeights(list(blocks)) for blocks in zip(*(m.blocks for m in members))]
        self.head = stacked([linear(m.head) for m in members])
        self.tau_mean = torch.stack([m.tau_mean for m in members])[:, None]
        self.tau_scale = torch.stack([m.tau_scale for m in members])[:, None]


def trimmed_mean(tau: Tensor) -> Tensor:
    """The ensemble's tau from its members' tau [K,...]: per frame, the mean of the members after dropping the
    lowest and the highest (K >= 3; the plain mean for K <= 2, a single model's tau itself for K = 1).

    A member validates on a fold of the takes that the others train on; the fold that holds the takes going
    furthest leaves its member extrapolating on a recording that goes as far, and that member alone can sit far
    off the others (1.6-1.9 of ridge where the rest score 0.6-0.9, ``benchmarks/README.md``, "Ensembles over
    seeds and folds").  Dropping the extremes frame by frame keeps the ensemble from following it.
    """
    if tau.shape[0] < 3:
        return tau.mean(0)
    return tau.sort(dim=0).values[1:-1].mean(0)


# members[0] -> (the members' parameters and their versions, the FrameWeights taken from them)
_SNAPSHOTS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def frame_weights(members: list[nn.Module]) -> FrameWeights:
    """The :class:`FrameWeights` of ``members``, one snapshot shared by every stream made while their parameters
    are unchanged (a phone per stream reads the same weights, which stay in the CPU's cache: four streams of an
    ensemble step about 30% faster than with a copy each); a parameter or buffer changed since (an optimiser
    step, a loaded state: its version counter moves; moved or cast: its storage) gives a new snapshot, and streams
    made before keep theirs."""
    key = tuple((id(t), t.data_ptr(), t.dtype, t._version)  # moved or cast (``.to``): other storage
                for member in members for t in (*member.parameters(), *member.buffers()))
    cached = _SNAPSHOTS.get(members[0])
    if cached is not None and cached[0] == key:
        return cached[1]
    weights = FrameWeights(members)
    _SNAPSHOTS[members[0]] = (key, weights)
    return weights


@dataclass
class EncodedFrame:
    """One frame's expression side, computed ahead by :meth:`LarynxStream.encode`: the members' features [K,B,d]
    and per block the cross-attention's output [K,B,d] (it depends on the expressions alone)."""

    memory: Tensor
    cross: list[Tensor]


class LarynxStream:
    """Live decoding, one frame at a time, at constant cost per frame and bounded memory.

    ``step(psi_t [B,55]) -> tau_t [B]`` (UV units): the members' tau combined by :func:`trimmed_mean` (one
    member for a single model, K for an ensemble, :mod:`.ensemble`), all members computed in the same calls.
    The stream keeps the expression encoder's state (:class:`~models.larynx.encoder.EncoderState`: convolution
    history, recurrent state, smoothed values, stacked over the members) and per block a :class:`BlockState` (a
    self-attention cache of ``window`` frames).  Nothing in it grows with the position (the tests measure it).

    The frames are computed from ``weights`` (:class:`FrameWeights`), a snapshot of the members' taken when the
    stream is made and shared with the other streams of the same weights (:func:`frame_weights`): make a new
    stream after training further.  Many frames given at once (:meth:`encode`, as
    :func:`generate` does) run the encoder's modules over all of them; the decoder always runs frame by frame.
    """

    def __init__(self, members: list[nn.Module], batch_size: int = 1, subject: Tensor | None = None):
        self.members = list(members)
        self.batch_size = batch_size
        first = self.members[0]
        cfg = first.cfg
        weight = next(first.parameters())
        dtype, device = weight.dtype, weight.device  # the stream lives where the models do
        self.weights = frame_weights(self.members)
        with torch.no_grad():
            self.token_base = torch.stack([m.token_base(batch_size, subject) for m in self.members]).to(dtype)
            self.gain = torch.stack([m.output_gain(batch_size, subject) for m in self.members]).to(dtype)  # [K,B,1]
        count = len(self.members) * batch_size  # the caches see the members' streams as one batch
        self.blocks = [BlockState.start(count, cfg.n_heads, cfg.d_model // cfg.n_heads, first.window, dtype,
                                        device) for _ in first.blocks]
        self.expression_state = stack_states([m.expression.initial_state(batch_size, dtype) for m in self.members])

    @torch.inference_mode()
    def encode(self, psi: Tensor) -> list[EncodedFrame]:
        """The expression side of frames psi [B,C,55] that continue the stream, one :class:`EncodedFrame`
        per frame (computed for all C frames at once, by each member's modules)."""
        memories, crosses, states = [], [], []
        for k, member in enumerate(self.members):
            memory, state = member.expression(psi, member_state(self.expression_state, k))
            memories.append(memory)
            crosses.append([block.cross(memory) for block in member.blocks])
            states.append(state)
        self.expression_state = stack_states(states)
        memory = torch.stack(memories).unbind(2)  # C of [K,B,d]
        cross = [torch.stack(per_block).unbind(2) for per_block in zip(*crosses)]
        return [EncodedFrame(m, [c[t] for c in cross]) for t, m in enumerate(memory)]

    @torch.inference_mode()
    def encode_frame(self, psi_t: Tensor) -> EncodedFrame:
        """The expression side of one frame psi_t [B,55] that continues the stream: what :meth:`encode` gives
        for a single frame, computed from :attr:`weights`."""
        memory, self.expression_state = encoder_frame(self.weights.encoder, self.expression_state, psi_t)
        return EncodedFrame(memory, [cross_frame(block, memory) for block in self.weights.blocks])

    @torch.inference_mode()
    def advance(self, frame: EncodedFrame) -> Tensor:
        """Decode the next frame from its encoded expressions (:meth:`encode`, :meth:`encode_frame`): each
        member's ``forward`` for one frame, from :attr:`weights` and the caches.

        Returns tau [B] (UV units), the members' :func:`trimmed_mean`.
        """
        x = self.token_base + frame.memory
        for weights, state, cross in zip(self.weights.blocks, self.blocks, frame.cross):
            x = block_frame(weights, state, x, cross)
        w = self.weights
        normalised = (torch.baddbmm(w.head[0], x, w.head[1]) * self.gain)[..., 0]  # [K,B]
        return trimmed_mean(torch.addcmul(w.tau_mean, w.tau_scale, normalised))

    @torch.inference_mode()
    def step(self, psi_t: Tensor) -> Tensor:
        """One live frame: psi_t [B,55] (or [55] for B = 1) -> tau_t [B] (UV units)."""
        dtype, device = self.token_base.dtype, self.token_base.device
        psi_t = torch.as_tensor(psi_t, dtype=dtype, device=device).reshape(self.batch_size, NUM_EXPRESSIONS)
        with single_thread():
            return self.advance(self.encode_frame(psi_t))


@torch.inference_mode()
def generate(stream: LarynxStream, psi: Tensor, chunk: int = 1024) -> Tensor:
    """tau [B,T] (UV units) from psi [B,T,55] through a new ``stream`` of batch B (any length).

    The expression side (encoder, cross-attention) is computed ``chunk`` frames at a time, the decoder
    frame by frame; memory is O(chunk + window) beyond input and output.
    """
    out = torch.empty(psi.shape[:2], dtype=psi.dtype, device=psi.device)
    for start in range(0, psi.shape[1], chunk):
        frames = stream.encode(psi[:, start:start + chunk])
        with single_thread():
            for t, frame in enumerate(frames):
                out[:, start + t] = stream.advance(frame)
    return out
