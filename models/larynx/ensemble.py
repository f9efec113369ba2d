"""An ensemble of larynx transformers: K members of the same sizes, trained from different seeds (and validation
folds), whose tau is averaged frame by frame without the lowest and the highest member
(:func:`~models.larynx.streaming.trimmed_mean`).

Which weights a run ends with depends on its seed and on the takes that chose its best step; on a new recording
that decides much of the error (``benchmarks/README.md``, "Expression -> larynx").  The mean of members trained
from independent seeds keeps what they share and averages away what the seed adds; dropping the lowest and the
highest per frame keeps one member that went astray (its validation fold held the takes it needed) out of it.
The members decode in the same calls (:class:`~models.larynx.streaming.LarynxStream`: every frame tensor carries
the members first), so a live frame of five costs about 1.5 of one member's.

The members share the subject table: rows are the union of their subjects, and a member that never trained on a
subject gives it its average person (:func:`with_subjects`).  Each keeps its own tau normalisation.
"""
from __future__ import annotations

import torch
from torch import Tensor, nn

from .model import STYLE_TABLES, LarynxTransformer, build_member
from .streaming import LarynxStream, generate, trimmed_mean


class LarynxEnsemble(nn.Module):
    """tau from psi as the trimmed mean of ``members``' (see the module docstring); the interface of
    :class:`LarynxTransformer` (``fps``, ``window``, ``subjects``, :meth:`subject_index`, ``forward``, :meth:`stream`,
    :meth:`generate`), so :func:`~models.larynx.model.predict_tau`, ``infer.py`` and the live receiver take either.

    Raises:
        ValueError: no members, or members of other sizes, rates or subject tables (naming the first that differs).
    """

    def __init__(self, members: list[LarynxTransformer]):
        super().__init__()
        if not members:
            raise ValueError("an ensemble needs at least one member")
        first = members[0]
        for k, member in enumerate(members[1:], 1):
            for what, mine, theirs in (("sizes", member.cfg, first.cfg), ("fps", member.fps, first.fps),
                                       ("subjects", member.subjects, first.subjects)):
                if mine != theirs:
                    raise ValueError(f"ensemble member {k} has other {what} than member 0: {mine} against {theirs}")
        self.members = nn.ModuleList(members)
        self.fps, self.window, self.subjects = first.fps, first.window, first.subjects

    @property
    def config(self) -> dict:
        """The checkpoint's ``model_config``: ``{"members": [each member's model_config]}`` (:func:`build_model`)."""
        return {"members": [member.config for member in self.members]}

    def subject_index(self, subject: str | None) -> int:
        """Style index of a subject name (0 for None = unknown subject); InputError for one no member knows."""
        return self.members[0].subject_index(subject)

    def forward(self, psi: Tensor, subject: Tensor | None = None) -> Tensor:
        """tau [B,T] (UV units): the members' (:meth:`LarynxTransformer.forward`) :func:`trimmed_mean`."""
        return trimmed_mean(torch.stack([member(psi, subject) for member in self.members]))

    def stream(self, batch_size: int = 1, subject: Tensor | None = None) -> LarynxStream:
        """A frame-by-frame decoder of all members at once (:class:`LarynxStream`)."""
        return LarynxStream(list(self.members), batch_size, subject)

    def generate(self, psi: Tensor, subject: Tensor | None = None, chunk: int = 1024) -> Tensor:
        """tau [B,T] (UV units) from psi [B,T,55], streamed (:func:`~models.larynx.streaming.generate`)."""
        return generate(self.stream(psi.shape[0], subject), psi, chunk)


def build_model(model_config: dict) -> nn.Module:
    """The model of a checkpoint's ``model_config``: with ``{"members": [configs]}`` alone a
    :class:`LarynxEnsemble`, else one :class:`LarynxTransformer` (:func:`~models.larynx.model.build_member`:
    ValueError for missing, unknown or removed options)."""
    if "members" not in model_config:
        return build_member(model_config)
    if set(model_config) != {"members"} or not model_config["members"]:
        raise ValueError(f"larynx ensemble config: keys {sorted(model_config)}, expected 'members' alone, a "
                         f"non-empty list of member configs")
    return LarynxEnsemble([build_member(config) for config in model_config["members"]])


def with_subjects(model: LarynxTransformer, subjects: list[str]) -> LarynxTransformer:
    """``model`` with the subject table ``subjects`` (a superset of its own, any order): each known subject keeps
    its rows of :data:`~models.larynx.model.STYLE_TABLES`, the others get the average person's (row 0)."""
    missing = [s for s in model.subjects if s not in subjects]
    if missing:
        raise ValueError(f"with_subjects: {missing} of the model are not in {subjects}")
    if list(subjects) == model.subjects:
        return model
    out = build_member({**model.config, "subjects": list(subjects)})
    state = model.state_dict()
    rows = torch.tensor([0] + [model.subject_index(s) if s in model.subjects else 0 for s in subjects])
    out.load_state_dict({k: v[rows] if k in STYLE_TABLES else v for k, v in state.items()})
    return out.to(next(model.parameters()).device)


def ensemble_of(members: list[LarynxTransformer]) -> LarynxEnsemble:
    """The ensemble of trained ``members`` (their subject tables joined, :func:`with_subjects`)."""
    subjects = sorted({s for member in members for s in member.subjects})
    return LarynxEnsemble([with_subjects(member, subjects).eval() for member in members])
