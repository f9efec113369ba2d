"""Synthetic normal-map sequences of the neck with the ground-truth larynx position, to test the tracker.

- :mod:`scene.normal_sequences.sequence`: a sequence made (head motion, expressions, tau, degradation) and written;
- :mod:`scene.normal_sequences.cli`: ``python -m scene.normal_sequences`` (its docstring: what a sequence holds).
"""

from scene.normal_sequences.cli import SequencesCli, run
from scene.normal_sequences.sequence import (
    SEQUENCE_FILES,
    SEQUENCE_FORMATS,
    NormalSequence,
    SequenceConfig,
    degrade,
    expression_window,
    head_motion,
    make_sequence,
    tau_r2,
    write_sequence,
)

__all__ = [
    "NormalSequence",
    "SEQUENCE_FILES",
    "SEQUENCE_FORMATS",
    "SequenceConfig",
    "SequencesCli",
    "degrade",
    "expression_window",
    "head_motion",
    "make_sequence",
    "run",
    "tau_r2",
    "write_sequence",
]
