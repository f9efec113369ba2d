"""The head2neck model (the shipped one or a checkpoint) and the rig whose bone frames it predicts in."""
from __future__ import annotations

from pathlib import Path

import torch

from models.checkpoint import load_model
from models.pretrained import NAMED, default_checkpoint, pretrained_path
from models.rig import HeadNeckModel


def load_head2neck(checkpoint: str | Path, rig_path: str | Path | None = None) -> tuple[torch.nn.Module, HeadNeckModel]:
    """A head2neck model (``"default"``: the shipped one; ``"hack"``: the shipped HACK-style one) and the rig
    ``rig_path`` (None: the built-in rig).

    The model holds nothing of a rig (``models.head2neck``): it reads the rig's joint rest frames when it
    runs, so any rig with HACK's 8-joint cervical chain serves."""
    if str(checkpoint) == "default":
        checkpoint = default_checkpoint("head2neck")
    elif str(checkpoint) in NAMED["head2neck"]:  # a shipped model by name (hack)
        checkpoint = pretrained_path(NAMED["head2neck"][str(checkpoint)])
    model, _ = load_model(checkpoint, task="head2neck")
    return model, HeadNeckModel.from_config(rig_path)
