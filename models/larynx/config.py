"""The larynx transformer's configuration: its sizes (hydra's ``model`` group) and what it takes from the data."""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field


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

    def __post_init__(self) -> None:
        if self.d_model % self.n_heads or (self.d_model // self.n_heads) % 2:
            raise ValueError(f"d_model {self.d_model} must split into {self.n_heads} heads of even size")
        for name in ("n_layers", "d_ff", "window", "expression_kernel"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be at least 1, got {getattr(self, name)}")
        if any(int(d) < 1 for d in self.expression_dilations):
            raise ValueError(f"expression_dilations must be positive, got {list(self.expression_dilations)}")
        if not 0.0 <= self.dropout < 1.0:
            raise ValueError(f"dropout must be in [0, 1), got {self.dropout}")


@dataclass
class LarynxDataFields:
    """What the model takes from its training data (filled in by the task, stored in the checkpoint)."""

    fps: float                 # frames per second of psi and tau
    subjects: list[str]        # training subject names: style index i+1 is subjects[i], 0 the unknown subject
    tau_mean: float            # tau normalisation (UV units)
    tau_scale: float


SIZES = tuple(f.name for f in dataclasses.fields(LarynxTransformerConfig))
DATA_KEYS = tuple(f.name for f in dataclasses.fields(LarynxDataFields))
