"""The models that ship with the project, under ``models/pretrained/``, and their manifest.

``models/pretrained/manifest.json`` lists each shipped file: what it is (``task``), the command and the
commit that produced it, its evaluation figures, and its sha256.  The files are weights-only
checkpoints (``models.checkpoint``: ``task``, ``model_config``, ``model``; no optimiser state), trained
by ``train.py`` on the built-in procedural rig and synthetic data only: nothing in them is derived from
the HACK release.  ``benchmarks/retrain_pretrained.py`` retrains them and compares with the manifest.

Shipping a trained run is release tooling, outside the product: ``python -m tools.ship_model`` (``tools/``).
Each task has a default model (``DEFAULTS``, a setting's ``default``) and may ship others by name
(``NAMED``: ``head2neck=hack`` is ``head2neck_hack.pt``, trained on the prior's HACK style).
"""
from __future__ import annotations

import hashlib
import json
import os
from pathlib import Path

from base.errors import InputError
from models.checkpoint import load_model

PRETRAINED = Path(__file__).resolve().parent
MANIFEST = PRETRAINED / "manifest.json"
# The default model of each task, used by infer.py when no checkpoint is given.
DEFAULTS = {"larynx_transformer": "larynx_transformer", "head2neck": "head2neck",
            "swallow_template": "swallow_template"}
# Other shipped models of a task, by the name a setting gives (infer.py's ``head2neck=hack``): {task: {name: entry}}.
# ``hack``: trained on the prior's HACK style (``data.prior.style=hack``, ``data.cervical_prior.hack``).
NAMED = {"head2neck": {"hack": "head2neck_hack"}}


def sha256(path: str | os.PathLike) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def read_manifest() -> dict:
    """The manifest: {name: {file, task, sha256, command, commit, eval, ...}}; {} when nothing ships."""
    if not MANIFEST.is_file():
        return {}
    try:
        return json.loads(MANIFEST.read_text())
    except json.JSONDecodeError as e:
        raise InputError(f"{MANIFEST}: not valid JSON ({e})") from None


def pretrained_path(name: str) -> Path:
    """The shipped checkpoint ``name`` after checking it against its manifest entry (file and sha256)."""
    manifest = read_manifest()
    if name not in manifest:
        raise InputError(f"no shipped model '{name}' in {MANIFEST} (shipped: {', '.join(manifest) or 'none'})")
    path = PRETRAINED / manifest[name]["file"]
    if not path.is_file():
        raise InputError(f"{path}: shipped model file missing (listed in {MANIFEST})")
    if sha256(path) != manifest[name]["sha256"]:
        raise InputError(f"{path}: sha256 differs from {MANIFEST}; the file is damaged or was replaced")
    return path


def default_checkpoint(task: str) -> Path:
    """The shipped default model of ``task``."""
    return pretrained_path(DEFAULTS[task])


def chosen_checkpoint(value: str | None, task: str, key: str, part: str,
                      announce=print) -> tuple[str | Path | None, str | None]:
    """The checkpoint a ``key=`` setting names for ``part`` (e.g. the larynx), and its provenance label:
    ``default`` is the shipped model of ``task`` (None, announced, when none ships), a name of ``NAMED[task]``
    (e.g. ``hack``) that shipped model, ``none`` (or null, or empty) is None (the part rests), anything else
    is the path given."""
    choice = "none" if value is None or str(value).lower() in ("none", "null", "") else str(value)
    if choice == "none":
        return None, None
    if choice in NAMED.get(task, {}):
        path = pretrained_path(NAMED[task][choice])
        announce(f"{part}: the shipped model {path.name} ({key}={choice})")
        return path, f"shipped:{path.name}"
    if choice != "default":
        return choice, choice
    if DEFAULTS[task] not in read_manifest():
        announce(f"{part}: no shipped model in models/pretrained; the {part} rests (give {key}=<file>)")
        return None, None
    path = default_checkpoint(task)
    announce(f"{part}: the shipped model {path.name} ({key}=<file> for another, {key}=none for none)")
    return path, f"shipped:{path.name}"


def load_default(task: str):
    """(model in eval mode, checkpoint dict) of the shipped default model of ``task``."""
    return load_model(default_checkpoint(task), task=task)
