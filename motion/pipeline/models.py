"""The models inference runs: the larynx model, the neck model, the rig and the character, as chosen."""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import torch

from models.checkpoint import load_model
from models.pretrained import chosen_checkpoint
from models.rig import HeadNeckModel
from motion.head2neck import load_head2neck
from motion.pipeline.config import InferConfig
from scene.characters import load_character


@dataclass
class Models:
    """What drives the neck: the larynx model, the neck model and the rig (theta is in its bone frames)."""

    rig: HeadNeckModel
    rig_name: str
    larynx: torch.nn.Module | None = None
    neck: torch.nn.Module | None = None
    producers: dict = field(default_factory=dict)
    character: HeadNeckModel | None = None  # the character the motion is retargeted onto (None: the rig's own)


def load_models(cfg: InferConfig, announce=print) -> Models:
    """The larynx and neck models ``cfg`` names (``default`` = shipped, ``none`` = at rest) and the rig."""
    larynx_path, larynx_from = chosen_checkpoint(cfg.checkpoint, "larynx_transformer", "checkpoint", "larynx",
                                                 announce)
    larynx = None if larynx_path is None else load_model(larynx_path, task="larynx_transformer")[0]
    neck_path, neck_from = chosen_checkpoint(cfg.head2neck, "head2neck", "head2neck", "neck", announce)
    producers = {"tool": "infer.py", "larynx": larynx_from, "head2neck": neck_from}
    producers = {key: value for key, value in producers.items() if value is not None}
    if neck_path is not None:
        neck, rig = load_head2neck(neck_path, cfg.rig)
    else:
        neck, rig = None, HeadNeckModel.from_config(cfg.rig)
    rig_name = "builtin" if cfg.rig in (None, "", "builtin") else str(Path(cfg.rig).resolve())
    character = None
    if cfg.character != "human":
        character = HeadNeckModel(load_character(cfg.character, rig.rig))
        announce(f"character: {cfg.character} ({character.num_vertices} vertices); the motion is retargeted onto it")
    return Models(rig, rig_name, larynx, neck, producers, character)
