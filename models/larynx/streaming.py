"""Live decoding of the larynx transformer: one frame at a time, at constant cost per frame and bounded memory.

:class:`LarynxStream` runs the model's ``forward`` frame by frame through the per-frame version of each module,
written beside it: :func:`~models.larynx.encoder.encoder_frame` (the expression encoder from its carried state),
:func:`~models.larynx.block.cross_frame` and :func:`~models.larynx.block.block_frame` (each block's
self-attention over a cache of ``window`` frames).  They compute from a snapshot of the weights laid out for
single-frame products (:class:`FrameWeights`, :mod:`.folding`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from base.threads import single_thread
from data.expressions import NUM_EXPRESSIONS

from .block import BlockFrameWeights, BlockState, block_frame, cross_frame
from .encoder import EncoderFrameWeights, encoder_frame
from .folding import linear

if TYPE_CHECKING:
    from .model import LarynxTransformer


class FrameWeights:
    """The weights of one live frame, taken from a model once per :class:`LarynxStream`: the encoder's
    (:class:`EncoderFrameWeights`), each block's (:class:`BlockFrameWeights`) and the head's."""

    def __init__(self, model: LarynxTransformer):
        self.encoder = EncoderFrameWeights(model.expression)
        self.blocks = [BlockFrameWeights(block) for block in model.blocks]
        self.head = linear(model.head)


@dataclass
class EncodedFrame:
    """One frame's expression side, computed ahead by :meth:`LarynxStream.encode`: its features [B,d] and per
    block the cross-attention's output [B,d] (it depends on the expressions alone)."""

    memory: Tensor
    cross: list[Tensor]


class LarynxStream:
    """Live decoding, one frame at a time, at constant cost per frame and bounded memory.

    ``step(psi_t [B,55]) -> tau_t [B]`` (UV units).  The stream keeps the expression encoder's state
    (:class:`~models.larynx.encoder.EncoderState`: convolution history, recurrent state, smoothed values) and per
    block a :class:`BlockState` (a self-attention cache of ``window`` frames).  Nothing in it grows with the
    position (:func:`tensor_bytes` measures it).

    The frames are computed from ``weights`` (:class:`FrameWeights`), a snapshot of the model's taken when
    the stream is made: make a new stream after training further.  Many frames given at once
    (:meth:`encode`, as :meth:`LarynxTransformer.generate` does) run the encoder's modules over all of them;
    the decoder always runs frame by frame.
    """

    def __init__(self, model: LarynxTransformer, batch_size: int = 1, subject: Tensor | None = None):
        self.model = model
        self.batch_size = batch_size
        cfg = model.cfg
        weight = next(model.parameters())
        dtype, device = weight.dtype, weight.device  # the stream lives where the model does
        self.weights = FrameWeights(model)
        with torch.no_grad():
            self.token_base = model.token_base(batch_size, subject).to(dtype)  # [B,d]
            self.gain = model.output_gain(batch_size, subject).to(dtype)  # [B,1]
        self.blocks = [BlockState.start(batch_size, cfg.n_heads, cfg.d_model // cfg.n_heads, model.window, dtype,
                                        device) for _ in model.blocks]
        self.expression_state = model.expression.initial_state(batch_size, dtype)

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
        cross = [block.cross(memory).unbind(1) for block in model.blocks]
        return [EncodedFrame(m, [c[t] for c in cross]) for t, m in enumerate(memory.unbind(1))]

    @torch.inference_mode()
    def encode_frame(self, psi_t: Tensor) -> EncodedFrame:
        """The expression side of one frame psi_t [B,55] that continues the stream: what :meth:`encode` gives
        for a single frame, computed from :attr:`weights`."""
        memory, self.expression_state = encoder_frame(self.weights.encoder, self.expression_state, psi_t)
        return EncodedFrame(memory, [cross_frame(block, memory) for block in self.weights.blocks])

    @torch.inference_mode()
    def advance(self, frame: EncodedFrame) -> Tensor:
        """Decode the next frame from its encoded expressions (:meth:`encode`, :meth:`encode_frame`): the
        decoder's ``forward`` for one frame, from :attr:`weights` and the caches.

        Returns the normalised prediction [B] ((tau - tau_mean) / tau_scale).
        """
        x = self.token_base + frame.memory
        for weights, state, cross in zip(self.weights.blocks, self.blocks, frame.cross):
            x = block_frame(weights, state, x, cross)
        head = self.weights.head
        return (torch.addmm(head[0], x, head[1]) * self.gain)[:, 0]

    @torch.inference_mode()
    def step(self, psi_t: Tensor) -> Tensor:
        """One live frame: psi_t [B,55] (or [55] for B = 1) -> tau_t [B] (UV units)."""
        dtype, device = self.token_base.dtype, self.token_base.device
        psi_t = torch.as_tensor(psi_t, dtype=dtype, device=device).reshape(self.batch_size, NUM_EXPRESSIONS)
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
