"""The larynx transformer: decoder blocks over expression features, its checkpoint builder and the tau of a take.

``forward`` runs whole sequences (training: nothing is fed back); ``generate`` and :func:`predict_tau` decode
through :class:`~models.larynx.streaming.LarynxStream`, which runs the per-frame version of each module.
"""
from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import Tensor, nn

from base.errors import InputError
from data.expressions import NUM_EXPRESSIONS

from .block import Block
from .config import DATA_KEYS, SIZES, LarynxDataFields, LarynxTransformerConfig
from .encoder import ExpressionEncoder
from .streaming import LarynxStream, generate


def constant_encoding(d_model: int) -> Tensor:
    """FaceFormer's sinusoidal positional encoding of a period of one frame: sin 0 and cos 0 of every
    frequency, i.e. [0, 1, 0, 1, ...] [d_model], the same for every frame."""
    out = torch.zeros(d_model)
    out[1::2] = 1.0
    return out


class LarynxTransformer(nn.Module):
    """tau from psi: decoder tokens of the expression features, a style per subject and a constant encoding,
    cross-attending to the expressions (see the package docstring).

    Args:
        cfg: the network's sizes.
        data: what it takes from the training data (rate, subjects, tau normalisation).
    """

    def __init__(self, cfg: LarynxTransformerConfig, data: LarynxDataFields):
        super().__init__()
        self.cfg, self.data = cfg, data
        d = cfg.d_model
        self.fps = float(data.fps)
        self.window = cfg.window
        self.subjects = [str(s) for s in data.subjects]
        self.register_buffer("tau_mean", torch.tensor(float(data.tau_mean)), persistent=False)
        self.register_buffer("tau_scale", torch.tensor(float(data.tau_scale)), persistent=False)
        self.register_buffer("positional", constant_encoding(d), persistent=False)
        self.expression = ExpressionEncoder(cfg)
        self.style = nn.Embedding(len(self.subjects) + 1, d)
        # Per-subject log gain of the output (people's larynx moves by different amounts for the same face:
        # a gain is a product, which the additive style of the tokens can only approximate); 0 = the average.
        self.style_gain = nn.Embedding(len(self.subjects) + 1, 1)
        self.blocks = nn.ModuleList(Block(cfg) for _ in range(cfg.n_layers))
        self.head = nn.Linear(d, 1)
        nn.init.zeros_(self.style.weight)
        nn.init.zeros_(self.style_gain.weight)
        nn.init.normal_(self.head.weight, std=0.01)
        nn.init.zeros_(self.head.bias)

    @property
    def config(self) -> dict:
        """The checkpoint's ``model_config``: the sizes and the data fields (what :func:`build_model` takes)."""
        return {**dataclasses.asdict(self.cfg), **dataclasses.asdict(self.data)}

    def subject_index(self, subject: str | None) -> int:
        """Style index of a subject name (0 for None = unknown subject)."""
        if subject is None:
            return 0
        if str(subject) not in self.subjects:
            known = ", ".join(self.subjects[:20]) + (" ..." if len(self.subjects) > 20 else "")
            raise InputError(f"subject '{subject}' was not in the training data (known: {known or 'none'}); "
                             f"leave subject unset for the average style")
        return self.subjects.index(str(subject)) + 1

    def token_base(self, batch_size: int, subject: Tensor | None) -> Tensor:
        """The part of the tokens that does not depend on psi: the constant encoding plus the style, [B,d]."""
        style = self.style.weight[:1] if subject is None else self.style(subject)  # [1 or B,d]
        return (self.positional + style).expand(batch_size, -1)

    def to_tau(self, normalised: Tensor) -> Tensor:
        """Normalised tau [...] (the network's output) -> tau [...] in UV units."""
        return self.tau_mean + self.tau_scale * normalised

    def output_gain(self, batch_size: int, subject: Tensor | None) -> Tensor:
        """The per-subject factor [B,1] of the normalised output (the unknown subject's for None)."""
        gain = self.style_gain.weight[:1] if subject is None else self.style_gain(subject)  # [1 or B,1]
        return torch.exp(gain).expand(batch_size, 1)

    def forward(self, psi: Tensor, subject: Tensor | None = None) -> Tensor:
        """tau [B,T] in UV units from psi [B,T,55] at ``fps`` and style indices subject [B] long (None: the
        unknown subject's style for all); frame t depends on psi[:, :t+1] only."""
        memory, _ = self.expression(psi)
        # The same token base for every frame, gathered rather than broadcast: the style's gradient then sums the
        # frames in the order it always did, and a seed trains the weights it trained before, bit for bit.
        every_frame = torch.zeros(memory.shape[1], dtype=torch.long, device=memory.device)
        x = self.token_base(memory.shape[0], subject)[:, None, :][:, every_frame] + memory
        for block in self.blocks:
            x = block(x, memory)
        return self.to_tau(self.head(x)[..., 0] * self.output_gain(x.shape[0], subject))

    def stream(self, batch_size: int = 1, subject: Tensor | None = None) -> LarynxStream:
        """A frame-by-frame decoder (see :class:`LarynxStream`; this model as an ensemble of one)."""
        return LarynxStream([self], batch_size, subject)

    def generate(self, psi: Tensor, subject: Tensor | None = None, chunk: int = 1024) -> Tensor:
        """tau [B,T] (UV units) from psi [B,T,55], streamed with the cache (any length; :func:`generate`)."""
        return generate(self.stream(psi.shape[0], subject), psi, chunk)


def build_member(model_config: dict) -> LarynxTransformer:
    """The network of ``model_config``: exactly the fields of :class:`LarynxTransformerConfig`
    (the sizes) and of :class:`LarynxDataFields` (from the training data); missing or unknown keys (an option
    an earlier version had), or sizes the config rejects, are a ValueError."""
    missing = [k for k in SIZES + DATA_KEYS if k not in model_config]
    unknown = sorted(set(model_config) - set(SIZES) - set(DATA_KEYS))
    if missing or unknown:
        raise ValueError(f"larynx transformer config: missing {missing}, unknown {unknown}; expected the sizes "
                         f"{list(SIZES)} (LarynxTransformerConfig) and the data's {list(DATA_KEYS)}")
    sizes = {k: model_config[k] for k in SIZES}
    sizes["expression_dilations"] = [int(d) for d in sizes["expression_dilations"]]
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
    extra = [k for k in source if k not in target]
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


def predict_tau(model: nn.Module, psi: np.ndarray, subject: str | None = None) -> np.ndarray:
    """The larynx slide of one recording, streamed (as live decoding would produce it).

    Args:
        model: a trained :class:`LarynxTransformer` or ensemble of them (:mod:`.ensemble`).
        psi: [T,55] expression weights at ``model.fps``, ``EXPRESSION_NAMES`` order.
        subject: a training subject's name for their style, or None for the average style.

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
    model.eval()
    tau = model.generate(torch.from_numpy(psi)[None].to(device), index)[0]
    return tau.cpu().numpy().astype(np.float64)
