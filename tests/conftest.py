"""Shared fixtures.  Tests that need the real HACK release read it from
``$HACK_ASSETS`` or ``../shared/assets`` beside the checkout and skip cleanly when absent."""
from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_ASSETS = Path(os.environ.get("HACK_ASSETS", REPO.parent / "shared" / "assets"))
HACK_DIR = SHARED_ASSETS / "HACK-Model"
ICT_DIR = SHARED_ASSETS / "ICT-FaceKit"
SAMPLES_DIR = SHARED_ASSETS.parent / "samples"

torch.set_num_threads(min(2, torch.get_num_threads()))


def shared_available() -> bool:
    return (HACK_DIR / "model" / "bones_neutral.json").is_file() and (ICT_DIR / "FaceXModel").is_dir()


requires_shared = pytest.mark.skipif(not shared_available(), reason=f"real HACK assets not found in {SHARED_ASSETS}")


@pytest.fixture(scope="session")
def builtin_rig():
    from models.rig import HeadNeckModel

    return HeadNeckModel.builtin()


@pytest.fixture(scope="session")
def real_rig_file(tmp_path_factory):
    """The real HACK release converted once per session to a rig file (outside the repository)."""
    if not shared_available():
        pytest.skip(f"real HACK assets not found in {SHARED_ASSETS}")
    from data.assets import convert

    out = tmp_path_factory.mktemp("rig") / "hack_rig.npz"
    convert(HACK_DIR, ICT_DIR, out)
    return out


@pytest.fixture(scope="session")
def real_rig(real_rig_file):
    from models.rig import HeadNeckModel

    return HeadNeckModel.load(real_rig_file)


@pytest.fixture(scope="session")
def livelinkface_samples() -> list[Path]:
    """The real Live Link Face recordings in ``../shared/samples/livelinkface`` (skips when absent)."""
    files = sorted((SAMPLES_DIR / "livelinkface").glob("*.csv"))
    if not files:
        pytest.skip(f"Live Link Face samples not found in {SAMPLES_DIR / 'livelinkface'}")
    return files
