"""Expression -> larynx transformer (after FaceFormer) with a streaming decoder of bounded cost.

FaceFormer (Fan et al., CVPR 2022) regresses motion with a transformer decoder: its tokens carry a positional
encoding and a style embedding, causal self-attention has an ALiBi-style bias, and the driving signal enters
through cross-attention aligned frame to frame.  Here the motion is the larynx slide tau and the driving signal
is the expression sequence psi.  Nothing depends on an absolute length: the attention biases are computed from
relative offsets and every attention looks at a fixed window of past frames, so

- the whole-sequence ``forward`` runs banded attention chunk by chunk (memory O(T * window));
- :class:`LarynxStream` decodes frame by frame with a key/value cache of ``window`` frames:
  each frame costs the same at frame 100 as at frame 100,000 and memory is bounded;
- FaceFormer's decoding (recompute the whole prefix at every frame) is the reference the cache must match
  (``tests/larynx_reference.py``).

Paired captures come in minutes, not hours, and the defaults (:class:`LarynxTransformerConfig`) are
chosen for that regime on real expressions (``benchmarks/bench_larynx_real.py``; figures in
``benchmarks/README.md``):
- the expression encoder (:mod:`.encoder`) is a stack of dilated causal convolutions (a receptive field of
  ``1 + (kernel-1) * sum(dilations)`` frames, about two seconds), a residual GRU layer (memory beyond
  any window: a swallow in progress, the time since the last one, effort building up over seconds;
  one cell step per live frame) and a bank of learnt first-order low-passes (:class:`Smoothing`: the
  larynx's inertia is one); its features are added to the decoder's tokens, so the self-attention
  window sees past expressions;
- a per-subject output gain (``style_gain``) beside the additive style: people differ by how far
  their larynx moves for the same face, a product;
- the attention bias falls per frame (ALiBi slopes 1/4 ... 1/256 per frame: time scales of 4 to 256 frames)
  and the positional encoding is one constant vector (FaceFormer's periodic encoding at a period of one frame:
  the period of speech-animation frames has no counterpart in the larynx);
- nothing is fed back: the tokens see past psi, not past tau (at inference a fed-back tau would be the
  model's own prediction, a function of the psi the tokens already see);
- one decoder block (as FaceFormer) and dropout 0.1;
- no LayerNorm before the head: the head reads the residual stream as it is, so a face that moves further
  than the training takes did can move tau further.

Modules: :mod:`.config` (sizes, data fields), :mod:`.attention`, :mod:`.encoder`, :mod:`.block` (each with the
per-frame version of its module beside it), :mod:`.folding` (weights laid out for one frame, the members of an
ensemble stacked), :mod:`.model` (the network, :func:`build_member`, :func:`transfer_weights`,
:func:`predict_tau`), :mod:`.ensemble` (K networks averaged, :func:`build_model` for either), :mod:`.streaming`
(:class:`LarynxStream`, one or K members per call).

Conventions (shapes carry a batch B and frames T):
- psi [B,T,55]: expression weights in ``data.expressions.EXPRESSION_NAMES`` order, at
  ``model.fps`` frames per second (the rate of the training data);
- tau [B,T]: larynx slide in UV units of the larynx map, + = up the neck (``data.synthetic_tau``).
  Inside the network tau is normalised, ``(tau - tau_mean) / tau_scale`` (both from the data);
- frame t's prediction depends on psi[:, :t+1] only (causal);
- subject [B] long: index into the style table, 0 = unknown subject (average style); names are
  ``model.subjects`` (index i+1 is ``subjects[i]``).
"""
from .config import SIZES, LarynxDataFields, LarynxTransformerConfig
from .ensemble import LarynxEnsemble, build_model, ensemble_of
from .model import LarynxTransformer, build_member, predict_tau, transfer_weights
from .streaming import LarynxStream, trimmed_mean

__all__ = [
    "SIZES", "LarynxDataFields", "LarynxEnsemble", "LarynxStream", "LarynxTransformer", "LarynxTransformerConfig",
    "build_member", "build_model", "ensemble_of", "predict_tau", "transfer_weights", "trimmed_mean",
]
