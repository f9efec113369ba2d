"""The model on the real HACK release (skipped when ../shared/assets is absent)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

from conftest import HACK_DIR, ICT_DIR, requires_shared

pytestmark = requires_shared

EXPRESSIONS = ["jawOpen", "mouthSmile_L", "eyeBlink_R", "cheekPuff_L", "browInnerUp_R", "mouthFunnel"]


@pytest.fixture(scope="module")
def reference():
    from reference_hack import ReleaseReference

    return ReleaseReference(HACK_DIR, ICT_DIR, EXPRESSIONS)


@pytest.mark.parametrize("seed, scale", [(0, 0.3), (1, 0.8), (2, 1.5)])
def test_forward_reproduces_the_release_reference(real_rig, reference, seed, scale):
    g = torch.Generator().manual_seed(seed)
    batch = 3
    theta = (torch.rand(batch, 8, 3, generator=g) - 0.5) * scale
    subset = torch.rand(batch, len(EXPRESSIONS), generator=g)
    psi = torch.zeros(batch, 55)
    psi[:, [real_rig.expression_names.index(n) for n in EXPRESSIONS]] = subset
    tau = (torch.rand(batch, generator=g) - 0.5) * 0.16
    eta = torch.rand(batch, generator=g) * 2
    ours = real_rig(theta, psi, tau, eta).double()
    theirs = reference(theta, subset, tau, eta)
    assert (ours - theirs).abs().max() < 1e-4  # cm


def test_real_larynx_slides_up_monotonically(real_rig):
    heights = []
    for tau in np.linspace(-0.05, 0.08, 14):
        offsets = real_rig.larynx_offsets(torch.tensor([tau], dtype=torch.float32), torch.ones(1))[0].norm(dim=1)
        heights.append(float((offsets * real_rig.template[:, 1]).sum() / offsets.sum()))
    assert (np.diff(heights) > 0).all()
    assert 0.8 < (heights[-1] - heights[0]) / (0.13 * 33.0) < 1.25  # ~33 cm of neck per UV unit


def test_real_rig_interface(real_rig):
    assert real_rig.num_vertices == 14062 and real_rig.faces.shape == (14034, 4)
    assert real_rig.joint_names[0] == "c7t1" and real_rig.joint_names[-1] == "oc1"
    assert torch.allclose(real_rig.head_rotation(real_rig.neutral(1)), torch.eye(3)[None], atol=1e-6)
