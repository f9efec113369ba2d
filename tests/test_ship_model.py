"""Shipping a finished run (tools/ship_model.py): the weights-only file, its manifest entry, the weights eval.json
scored, and the refusal of an unfinished run; into a temporary models/pretrained/."""
from __future__ import annotations

import hashlib
import json
import re
import subprocess
import sys

import pytest
import torch

from base.errors import InputError
from models import pretrained
from models.checkpoint import save_checkpoint
from models.head2neck import Head2NeckConfig, Head2NeckMLP, model_config
from tests.conftest import REPO
from tools import ship_model

EVALUATION = {"val_joint_error_deg": 1.25, "steps": 7}


@pytest.fixture
def shipped_folder(tmp_path, monkeypatch):
    folder = tmp_path / "pretrained"
    folder.mkdir()
    for module in (pretrained, ship_model):
        monkeypatch.setattr(module, "PRETRAINED", folder)
        monkeypatch.setattr(module, "MANIFEST", folder / "manifest.json")
    return folder


def finished_run(root, restore_best: bool, evaluated: bool = True):
    """A run folder as train.py leaves it: last.pt (with optimiser state and config), best.pt, eval.json."""
    run = root / "run"
    torch.manual_seed(0)
    weights = {}
    for name in ("last", "best"):
        model = Head2NeckMLP(Head2NeckConfig(hidden=[8]))
        weights[name] = model.state_dict()
        save_checkpoint(run / "checkpoints" / f"{name}.pt",
                        {"task": "head2neck", "model_config": model_config(model), "model": weights[name],
                         "step": 7, "optimizer": {"state": {}}, "config": {"trainer": {"restore_best": restore_best}}})
    if evaluated:
        (run / "eval.json").write_text(json.dumps(EVALUATION))
    return run, weights


@pytest.mark.parametrize("restore_best", [True, False])
def test_ship_writes_the_evaluated_weights_and_their_manifest_entry(tmp_path, shipped_folder, restore_best):
    run, weights = finished_run(tmp_path, restore_best)
    entry = ship_model.ship(run, "neck_test", "python train.py task=head2neck")
    path = shipped_folder / "neck_test.pt"
    assert entry["file"] == path.name and entry["sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert entry["eval"] == EVALUATION and entry["task"] == "head2neck" and entry["bytes"] == path.stat().st_size
    assert re.fullmatch(r"[0-9a-f]{40}(\+uncommitted changes)?|unknown", entry["commit"])
    state = torch.load(path, weights_only=True)
    assert set(state) == {"task", "model_config", "model", "step"}  # no optimiser state, no run config
    scored = weights["best" if restore_best else "last"]
    assert all(torch.equal(state["model"][k], v) for k, v in scored.items())
    assert pretrained.pretrained_path("neck_test") == path  # the manifest entry verifies the file


def test_an_unfinished_run_is_refused(tmp_path, shipped_folder):
    run, _ = finished_run(tmp_path, restore_best=False, evaluated=False)
    with pytest.raises(InputError, match=r"eval\.json: not found; ship a finished run"):
        ship_model.ship(run, "neck_test", "python train.py")
    assert not (shipped_folder / "neck_test.pt").exists() and not (shipped_folder / "manifest.json").exists()


def test_the_command_needs_run_name_and_command():
    result = subprocess.run([sys.executable, "-m", "tools.ship_model", "name=x"], cwd=REPO, capture_output=True,
                            text=True, timeout=120)
    assert result.returncode == 2 and "missing run=..., command=..." in result.stderr
