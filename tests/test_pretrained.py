"""The shipped models: present, matching their manifest, small, and rebuilt by the code."""
from __future__ import annotations

import hashlib
import json

import pytest
import torch

from base.errors import InputError
from models import pretrained
from models.checkpoint import load_model

MANIFEST = pretrained.PRETRAINED / "manifest.json"


def entries() -> dict:
    return json.loads(MANIFEST.read_text()) if MANIFEST.is_file() else {}


@pytest.mark.parametrize("task", ["larynx_transformer", "head2neck"])
def test_each_task_ships_a_default_model_matching_the_manifest(task):
    manifest = entries()
    name = pretrained.DEFAULTS[task]
    assert name in manifest, f"no shipped {task} model in {MANIFEST}"
    entry = manifest[name]
    path = pretrained.PRETRAINED / entry["file"]
    assert hashlib.sha256(path.read_bytes()).hexdigest() == entry["sha256"]
    assert path.stat().st_size == entry["bytes"] < 5_000_000  # a few MB at most
    assert entry["task"] == task and entry["command"].startswith("python train.py")
    assert "no third-party data" in entry["trained_on"] and entry["eval"]
    state = torch.load(path, map_location="cpu", weights_only=True)
    assert set(state) == {"task", "model_config", "model", "step"}  # weights only: no optimiser state
    model, _ = load_model(path, task=task)
    assert not model.training and sum(p.numel() for p in model.parameters()) > 1000


def test_a_damaged_shipped_file_is_refused(tmp_path, monkeypatch):
    manifest = entries()
    name, entry = next(iter(manifest.items()))
    copy = tmp_path / entry["file"]
    copy.write_bytes((pretrained.PRETRAINED / entry["file"]).read_bytes()[:-10] + b"0123456789")
    (tmp_path / "manifest.json").write_text(json.dumps(manifest))
    monkeypatch.setattr(pretrained, "PRETRAINED", tmp_path)
    monkeypatch.setattr(pretrained, "MANIFEST", tmp_path / "manifest.json")
    with pytest.raises(InputError, match=r"sha256 differs from .*manifest\.json; the file is damaged or was replaced"):
        pretrained.pretrained_path(name)
    with pytest.raises(InputError, match=r"no shipped model 'nothing'"):
        pretrained.pretrained_path("nothing")
