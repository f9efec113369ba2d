"""The hydra schemas of ``task=larynx_transformer``: the task, its data kinds, and the model sizes' schema."""
from __future__ import annotations

from dataclasses import dataclass, field

from base.cli import REQUIRED, register_config
from models.larynx import LarynxTransformerConfig


@dataclass
class LarynxTaskConfig:
    """``task=larynx_transformer``: crops, losses, the length of training, the baselines, the starting point."""

    name: str = "larynx_transformer"
    # Frames per training crop (must exceed model.window; the longest sequence's length when all are shorter).
    # The recurrent state runs from the crop's start, and at inference over whole takes: crops of 12.8 s
    # let it learn drives that build up over seconds (benchmarks/README.md, "Expression -> larynx").
    crop: int = 384
    batch_size: int = 16
    style_dropout: float = 0.25   # share of crops trained with the unknown-subject style (used for new subjects)
    velocity_weight: float = 0.5  # weight of the frame-difference MSE
    # Weight of a group lasso on the expression projection: the sum over expression channels of the norm of
    # each channel's input weights.  The larynx follows a few articulators; this shrinks the weights of the
    # others towards zero, so channels that only happen to co-vary with tau in few recordings, or that another
    # capture moves elsewhere, are not leant on (real-regime benchmark, seeds 0-3: better or equal on every
    # family, benchmarks/README.md).
    input_sparsity: float = 0.01
    # The length the task chooses (trainer.max_steps null): epochs passes over the training frames, within
    # [fewest_steps, most_steps].
    epochs: float = 300.0
    fewest_steps: int = 600
    most_steps: int = 2000
    eval_batch: int = 32          # validation sequences decoded together
    ridge_window: float = 1.0     # seconds of psi the ridge baseline sees
    ridge_lambdas: list[float] = field(default_factory=lambda: [0.01, 0.1, 1.0, 10.0, 100.0, 1000.0, 1e4, 1e5])
    # Weights to start from instead of a random initialisation: a larynx_transformer checkpoint of the same
    # model sizes, or "pretrained" for the shipped model (trained on data=synthetic); see warm_start.
    init_from: str | None = None
    # An ensemble of this many networks (tasks.members): member k trains from its own seed (k = 0: ``seed`` itself)
    # and, on data=pairs, validates on its own fold of the takes (the k-th run of data.val_fraction of them, so
    # fold 0 is the split of a single network); the run's checkpoint averages them, decoded live as one batched
    # step.  Single networks' held-out error depends on the seed about as much as on the method
    # (benchmarks/README.md, "Ensembles over seeds and folds").
    members: int = 5
    member: int | None = None     # train this member alone (set for each member by the run; null: all of them)
    # An ensemble (members > 1) on data=pairs, where each member's validation fold is taken from the training takes:
    # the fold only chooses how many steps the member trains (its best step), then the member trains again on every
    # take for that many steps (tasks.members, "Refitting"), so no member goes without the takes of its fold.
    refit: bool = True
    refit_steps: int | None = None  # set by the run for a member's refit: train on every take for this many steps

    def __post_init__(self):
        if self.members < 1:
            raise ValueError(f"members is {self.members}, expected at least 1")
        if self.member is not None and not 0 <= self.member < self.members:
            raise ValueError(f"member is {self.member}, expected 0 <= member < members ({self.members}) or null")
        if self.refit_steps is not None and self.refit_steps < 1:
            raise ValueError(f"refit_steps is {self.refit_steps}, expected at least 1 or null")


@dataclass
class SyntheticData:
    """``data=synthetic``: talking faces and the larynx they drive (``data.synthetic_larynx``)."""

    kind: str = "synthetic"
    fps: float = 30.0
    seconds: float = 20.0                  # length of each sequence
    train_subjects: int = 24
    sequences_per_subject: int = 6
    new_takes_per_subject: int = 1         # validation: new recordings of the training subjects, and ...
    heldout_subjects: int = 6              # ... subjects never seen in training ...
    heldout_sequences_per_subject: int = 3
    heldout_shift: float = 1.0             # ... from a generator shifted this far (0: the training generator)
    seed: int = 0                          # data seed (independent of the training seed)
    tau_noise: float = 0.0005              # std of white tracker noise on tau (UV units; 0.03 ~ 1 cm)
    swallows_per_minute: float = 8.0       # swallows are placed in pauses of speech at about this rate
    blinks_per_minute: float = 15.0
    expression_noise: float = 0.01         # std of white tracker noise on each expression weight
    repeat_seals: float = 0.4              # share of swallows followed by a second seal (a swallow only
                                           # after the subject's refractory time)
    # What each person's swallows follow, drawn per person from these kinds (data.synthetic_larynx.SWALLOW_CUES:
    # seal, pause, snap, blink); every held-out person too.  One kind by default: with several, the model does
    # not learn whose swallows follow what (benchmarks/README.md, "Swallow cues").
    swallow_cues: list[str] = field(default_factory=lambda: ["seal"])


@dataclass
class PairsData:
    """``data=pairs``: a folder of pair files (``python -m data.pairs``), split by take."""

    kind: str = "pairs"
    path: str = REQUIRED
    fps: float = 30.0                      # every file is resampled to this rate
    val_fraction: float = 0.2              # share of takes held out for validation
    split_seed: int = 0


register_config("larynx_transformer_model_schema", LarynxTransformerConfig, group="model")
register_config("larynx_transformer_task_schema", LarynxTaskConfig, group="task")
register_config("larynx_transformer_synthetic_schema", SyntheticData, group="data_task")
register_config("larynx_transformer_pairs_schema", PairsData, group="data_task")
DATA_KINDS = {"synthetic": SyntheticData, "pairs": PairsData}
