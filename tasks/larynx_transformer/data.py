"""The sequences of ``task=larynx_transformer``: training and validation sets of each data kind, and the crops.

A run loads its sequences once (:func:`load_data`: :class:`LarynxData`); an ensemble's members share them, each
training and validating on index sets of them (its fold).

- ``data=synthetic`` (:class:`SyntheticData`): ``data.synthetic_larynx`` sequences.  Validation is on new
  recordings of the training subjects (with their style) and on held-out subjects drawn from a *shifted*
  generator (``data.heldout_shift``);
- ``data=pairs`` (:class:`PairsData`): a folder of pair files, split into training and validation by take.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

from base.cli import to_dataclass
from base.errors import InputError
from data.pairs import LarynxSequence, load_pairs, split_by_take
from data.synthetic_larynx import (
    SWALLOW_CUES,
    TRAINING_RANGES,
    GeneratorRanges,
    heldout_ranges,
    make_dataset,
    make_sequence,
    split_subjects,
)

from .config import DATA_KINDS, PairsData, SyntheticData


def data_settings(data) -> SyntheticData | PairsData:
    """``cfg.data`` as the dataclass of its kind; InputError for another kind."""
    kind = data.kind if hasattr(data, "kind") else data["kind"]
    if kind not in DATA_KINDS:
        raise InputError(f"larynx_transformer: data.kind '{kind}' not supported ({' or '.join(DATA_KINDS)})")
    return data if isinstance(data, DATA_KINDS[kind]) else to_dataclass(data, DATA_KINDS[kind], where="data")


def load_sequences(data, fold: int = 0, folds: int = 1) -> tuple[list[LarynxSequence], list[LarynxSequence]]:
    """(training, validation) sequences for ``cfg.data``, at ``data.fps``; ``data=pairs`` validates on fold ``fold``
    of ``folds`` of the takes (an ensemble's member, :func:`data.splits.split_by_file`), ``data=synthetic`` on its
    own validation people whatever the fold."""
    data = data_settings(data)
    if data.kind == "synthetic":
        train_ids, heldout_ids = split_subjects(data.train_subjects, data.heldout_subjects)
        options = synthetic_options(data)
        train = synthetic_training_sequences(data, data.fps)
        frames = int(round(data.seconds * data.fps))
        new_takes = [make_sequence(subject, data.sequences_per_subject + i, frames, data.fps, data.seed, **options)
                     for subject in train_ids for i in range(data.new_takes_per_subject)]
        new_people = make_dataset(heldout_ids, data.heldout_sequences_per_subject, data.seconds, data.fps, data.seed,
                                  **{**options, "ranges": with_cues(heldout_ranges(data.heldout_shift), data)})
        return train, new_takes + new_people
    return split_sequences(data, load_pairs(data.path, data.fps), fold, folds)


def split_sequences(data: PairsData, pairs: list[LarynxSequence], fold: int, folds: int
                    ) -> tuple[list[LarynxSequence], list[LarynxSequence]]:
    """(training, validation) of ``pairs`` for fold ``fold`` of ``folds``: :func:`data.pairs.split_by_take`."""
    return split_by_take(pairs, float(data.val_fraction), int(data.split_seed), f"take in {data.path}", fold, folds)


@dataclass
class LarynxData:
    """Every sequence of a run and each member's (training, validation) indices into them.

    ``folds[k]`` is member k's; on ``data=synthetic`` every member has the same (``shared_validation``).
    ``baselines`` holds the baselines scored so far (``task.baselines``: the ridge is fitted once per training
    set in a run).
    """

    sequences: list[LarynxSequence]
    folds: list[tuple[list[int], list[int]]]
    shared_validation: bool
    baselines: dict[tuple, dict[str, float]] = field(default_factory=dict)

    def fold(self, member: int) -> tuple[list[LarynxSequence], list[LarynxSequence]]:
        """(training, validation) sequences of member ``member``."""
        train, val = self.folds[member]
        return [self.sequences[i] for i in train], [self.sequences[i] for i in val]


def load_data(cfg) -> LarynxData:
    """The sequences of ``cfg.data`` and the folds of the ``task.members`` members (:func:`load_sequences`)."""
    members, data = int(cfg.task.get("members", 1)), data_settings(cfg.data)
    if data.kind == "synthetic":
        train, val = load_sequences(data)
        indices = (list(range(len(train))), list(range(len(train), len(train) + len(val))))
        return LarynxData(train + val, [indices] * members, True)
    sequences = load_pairs(data.path, data.fps)
    index = {id(s): i for i, s in enumerate(sequences)}
    folds = []
    for k in range(members):
        train, val = split_sequences(data, sequences, k, members)
        folds.append(([index[id(s)] for s in train], [index[id(s)] for s in val]))
    return LarynxData(sequences, folds, False)


def with_cues(ranges: GeneratorRanges, data: SyntheticData) -> GeneratorRanges:
    """``ranges`` whose people swallow at the kinds of ``data.swallow_cues``; InputError naming an unknown kind."""
    cues = tuple(str(c) for c in data.swallow_cues)
    unknown = [c for c in cues if c not in SWALLOW_CUES]
    if unknown or not cues:
        raise InputError(f"data.swallow_cues: {', '.join(unknown) or 'empty'}; expected some of "
                         f"{', '.join(SWALLOW_CUES)}")
    return dataclasses.replace(ranges, cues=cues)


def synthetic_options(data: SyntheticData) -> dict:
    """The generator options of ``data`` (:func:`data.synthetic_larynx.make_sequence`'s keywords; the training
    people's ranges)."""
    return {"tau_noise": data.tau_noise, "swallows_per_minute": data.swallows_per_minute,
            "blinks_per_minute": data.blinks_per_minute, "expression_noise": data.expression_noise,
            "repeat_seals": data.repeat_seals, "ranges": with_cues(TRAINING_RANGES, data)}


def synthetic_training_sequences(data: SyntheticData, fps: float) -> list[LarynxSequence]:
    """The training people's sequences of ``data`` (``data=synthetic``), generated at ``fps``."""
    train_ids, _ = split_subjects(data.train_subjects, data.heldout_subjects)
    return make_dataset(train_ids, data.sequences_per_subject, data.seconds, fps, data.seed, **synthetic_options(data))


def crop_for(train: list[LarynxSequence], crop: int, window: int) -> int:
    """The training crop: ``task.crop`` frames, or the longest training sequence when all are shorter
    (printed); InputError when even that does not exceed ``model.window``."""
    longest = max(len(s) for s in train)
    if longest <= window:
        raise InputError(f"no training sequence is longer than model.window={window} frames (longest: {longest}); "
                         f"training needs crops of full attention windows: lower model.window")
    if longest < crop:
        print(f"larynx_transformer: every training sequence is shorter than task.crop={crop} frames: crops of "
              f"{longest} frames (the longest)")
    return min(crop, longest)
