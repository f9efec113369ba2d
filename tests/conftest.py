"""Shared fixtures and published constants.  Tests that need the real HACK release read it from
``$HACK_ASSETS`` or ``../shared/assets`` beside the checkout and skip cleanly when absent."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import numpy as np
import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SHARED_ASSETS = Path(os.environ.get("HACK_ASSETS", REPO.parent / "shared" / "assets"))
HACK_DIR = SHARED_ASSETS / "HACK-Model"
ICT_DIR = SHARED_ASSETS / "ICT-FaceKit"
SAMPLES_DIR = SHARED_ASSETS.parent / "samples"

torch.set_num_threads(min(2, torch.get_num_threads()))

# Published cervical ranges of motion, degrees, root to head (C7-T1, C6-C7, C5-C6, C4-C5, C3-C4, C2-C3,
# C1-C2, O-C1), typed from the sources (not from data/joint_limits.py, which they check):
# axial rotation to one side, White & Panjabi, Clinical Biomechanics of the Spine, 2nd ed. 1990,
# tables 2-1 and 2-3;
AXIAL_ONE_SIDE = np.array([2, 6, 7, 7, 7, 3, 40, 5], float)
# combined flexion + extension: White & Panjabi 1990 below C2; C1-C2 11.5 + 10.9 and O-C1 3.5 + 21.0
# from Panjabi et al., Spine 13(7):726-730, 1988.
SAGITTAL_TOTAL = np.array([9, 17, 20, 20, 15, 10, 22.4, 24.5])

# Quarter turns: the columns are the images of x, y, z.
QUARTER_TURN_X = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # y -> z, z -> -y
QUARTER_TURN_Y = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])  # z -> x, x -> -z


def shared_available() -> bool:
    return (HACK_DIR / "model" / "bones_neutral.json").is_file() and (ICT_DIR / "FaceXModel").is_dir()


requires_shared = pytest.mark.skipif(not shared_available(), reason=f"real HACK assets not found in {SHARED_ASSETS}")


@pytest.fixture(scope="session")
def builtin_rig():
    from models.rig import HeadNeckModel

    return HeadNeckModel.builtin()


@pytest.fixture(scope="session")
def short(builtin_rig):
    """12 small normal-map frames of the built-in rig (noise-free, 128x128 at 0.12 cm/px), for the tracker's
    readers and command line."""
    from scene.normal_sequences import SequenceConfig, make_sequence

    cfg = SequenceConfig(frames=12, size=128, cm_per_px=0.12, noise=0.0, head_motion_deg=0.0)
    return make_sequence(builtin_rig, cfg, seed=2)


def turn_bone_frames(rig, turns: dict[str, np.ndarray]):
    """The RigData ``rig`` with bone j's rest frame turned by ``turns[name_j]`` ([3,3]; its axes become
    ``R_j @ Q_j``) about its origin, its children's rest transforms re-expressed in the turned frame: the
    same skeleton and mesh at rest, other bone-frame axes."""
    turn = [np.asarray(turns.get(str(name), np.eye(3))) for name in rig.joint_names]
    local = rig.joint_rest_local.astype(np.float64).copy()
    for j, parent in enumerate(rig.parents):
        parent_turn = turn[parent] if parent >= 0 else np.eye(3)
        local[j, :3, :3] = parent_turn.T @ local[j, :3, :3] @ turn[j]
        local[j, :3, 3] = parent_turn.T @ local[j, :3, 3]
    return dataclasses.replace(rig, joint_rest_local=local.astype(rig.joint_rest_local.dtype))


@pytest.fixture(scope="session")
def turned_rig_file(tmp_path_factory, builtin_rig):
    """A rig file of the built-in rig whose oc1 bone points into the face, as the release's does (its y
    axis turned from up to forward), and whose c1c2 bone is turned a quarter about y: the anatomical
    axes of two joints are not the bone axes (on the built-in rig they all are)."""
    out = tmp_path_factory.mktemp("turned_rig") / "turned_rig.npz"
    turn_bone_frames(builtin_rig.rig, {"oc1": QUARTER_TURN_X, "c1c2": QUARTER_TURN_Y}).save(out)
    return out


@pytest.fixture(scope="session")
def turned_rig(turned_rig_file):
    from models.rig import HeadNeckModel

    return HeadNeckModel.load(turned_rig_file)


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
