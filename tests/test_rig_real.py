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


def test_anatomical_frames_turn_the_release_oc1_upright(real_rig):
    """The release's oc1 bone points into the face; its anatomical frame is the quarter turn that
    makes +x flexion, +y axial rotation (to the subject's left), +z lateral bending, as for the others."""
    assert torch.allclose(real_rig.anatomical_axes[:-1], torch.eye(3).expand(7, 3, 3))
    assert torch.allclose(real_rig.anatomical_rest_rotations[-1], torch.eye(3), atol=1e-5)
    nose = int(torch.argmax(real_rig.template[:, 2]))
    crown = int(torch.argmax(real_rig.template[:, 1]))
    # flexion: the nose goes down; axial rotation: the nose turns to +x; lateral bending: the crown tips to -x
    for axis, vertex, coordinate, sign in ((0, nose, 1, -1.0), (1, nose, 0, 1.0), (2, crown, 0, -1.0)):
        theta = torch.zeros(1, 8, 3)
        theta[0, -1, axis] = 0.2  # oc1 alone, in its anatomical frame
        posed = real_rig(real_rig.from_anatomical(theta), eta=torch.zeros(1))[0, vertex]
        assert sign * (posed - real_rig.template[vertex])[coordinate] > 1.0, axis


@pytest.mark.parametrize("threads", [1, 2])
def test_threaded_batch_reproduces_the_release_reference(real_rig, reference, threads):
    """A batch of 10 frames (several vertex chunks, on 2 threads split between them), poses up to 0.6 rad per
    axis, taus over the whole slide, with and without autograd recording."""
    g = torch.Generator().manual_seed(7)
    batch = 10
    theta = (torch.rand(batch, 8, 3, generator=g) - 0.5) * 1.2
    subset = torch.rand(batch, len(EXPRESSIONS), generator=g)
    psi = torch.zeros(batch, 55)
    psi[:, [real_rig.expression_names.index(n) for n in EXPRESSIONS]] = subset
    tau = torch.linspace(-0.12, 0.15, batch)
    eta = torch.rand(batch, generator=g) * 2
    theirs = reference(theta, subset, tau, eta)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.no_grad():
            ours = real_rig(theta, psi, tau, eta)
        recorded = real_rig(theta, psi.requires_grad_(True), tau, eta)
    finally:
        torch.set_num_threads(before)
    assert (ours.double() - theirs).abs().max() < 1e-4  # cm
    assert torch.equal(recorded.detach(), ours)
