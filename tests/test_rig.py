"""The head-and-neck model on the built-in procedural rig: conventions, kinematics, gradients, errors."""
from __future__ import annotations

import dataclasses
import threading

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from data.expressions import EXPRESSION_NAMES
from data.procedural_rig import Y_BOTTOM, Y_CAP, Y_TOP
from models.rig import HeadNeckModel, linear_blend_skinning, skinning_transforms


def random_inputs(model: HeadNeckModel, batch: int, seed: int = 0, scale: float = 0.3):
    g = torch.Generator().manual_seed(seed)
    theta = (torch.rand(batch, model.num_joints, 3, generator=g) - 0.5) * scale
    psi = torch.rand(batch, model.num_expressions, generator=g)
    tau = (torch.rand(batch, generator=g) - 0.5) * 0.1
    eta = torch.rand(batch, generator=g) * 1.5
    beta = torch.randn(batch, model.num_shapes, generator=g)
    return theta, psi, tau, eta, beta


def larynx_height(model: HeadNeckModel, tau: float) -> float:
    """Height (cm) of the displacement-weighted centroid of the larynx term."""
    offsets = model.larynx_offsets(torch.tensor([tau]), torch.ones(1))[0].norm(dim=1)
    return float((offsets * model.template[:, 1]).sum() / offsets.sum())


def test_builtin_is_a_few_thousand_vertices_with_the_hack_interface(builtin_rig):
    assert 2000 < builtin_rig.num_vertices < 10000
    assert builtin_rig.joint_names == ["c7t1", "c6c7", "c5c6", "c4c5", "c3c4", "c2c3", "c1c2", "oc1"]
    assert builtin_rig.parents == [-1, 0, 1, 2, 3, 4, 5, 6]
    assert builtin_rig.expression_names == list(EXPRESSION_NAMES)
    assert builtin_rig.faces.shape[1] == 3 and int(builtin_rig.faces.max()) == builtin_rig.num_vertices - 1


def test_rest_pose_gives_the_template(builtin_rig):
    theta = builtin_rig.neutral(2)
    without_larynx = builtin_rig(theta, eta=torch.zeros(2))
    assert torch.allclose(without_larynx, builtin_rig.template.expand(2, -1, -1), atol=1e-5)
    with_larynx = builtin_rig(theta)
    expected = builtin_rig.template + builtin_rig.larynx_offsets(torch.zeros(1), torch.ones(1))[0]
    assert torch.allclose(with_larynx[0], expected, atol=1e-5)
    assert float((with_larynx[0] - builtin_rig.template).norm(dim=1).max()) > 0.5  # the larynx protrudes


def test_larynx_moves_monotonically_up_the_neck_with_tau(builtin_rig):
    taus = np.linspace(-0.06, 0.10, 17)
    heights = np.array([larynx_height(builtin_rig, t) for t in taus])
    assert (np.diff(heights) > 0).all()
    # Derived from the construction (data/procedural_rig.py, body_surface): every vertex below the crown has
    # v = (y - Y_BOTTOM) / (Y_TOP - Y_BOTTOM), so sliding the map by tau in v slides the larynx by
    # tau (Y_TOP - Y_BOTTOM) = tau (14.5 + 19.0) cm: 33.5 cm per UV unit.  The centroid of the bump sampled
    # at rows 29/60 cm apart follows a slide to ~1e-3 cm, i.e. the fitted slope to ~0.01 cm per unit.
    assert Y_TOP - Y_BOTTOM == 33.5
    below_crown = builtin_rig.template[:, 1] < Y_CAP
    uv = torch.tensor(builtin_rig.rig.vertex_uv)[below_crown]
    assert torch.allclose(uv[:, 1], (builtin_rig.template[below_crown, 1] - Y_BOTTOM) / 33.5, atol=1e-6)
    slope = np.polyfit(taus, heights, 1)[0]
    assert slope == pytest.approx(33.5, abs=0.05)


def test_batch_matches_single_frames(builtin_rig):
    theta, psi, tau, eta, beta = random_inputs(builtin_rig, 5)
    batched = builtin_rig(theta, psi, tau, eta, beta)
    for i in range(5):
        single = builtin_rig(theta[i:i + 1], psi[i:i + 1], tau[i:i + 1], eta[i:i + 1], beta[i:i + 1])
        assert torch.allclose(batched[i], single[0], atol=1e-5)


def test_joint_transforms_keep_bone_lengths_and_start_at_rest(builtin_rig):
    theta, *_ = random_inputs(builtin_rig, 6, scale=1.0)
    world = builtin_rig.joint_transforms(theta)
    assert world.shape == (6, 8, 4, 4)
    rest = builtin_rig.joint_transforms(builtin_rig.neutral(1))[0]
    assert torch.allclose(rest, builtin_rig.rest_world, atol=1e-6)
    lengths = (world[:, 1:, :3, 3] - world[:, :-1, :3, 3]).norm(dim=-1)
    rest_lengths = (rest[1:, :3, 3] - rest[:-1, :3, 3]).norm(dim=-1)
    assert torch.allclose(lengths, rest_lengths.expand_as(lengths), atol=1e-5)
    rotations = world[..., :3, :3]
    assert torch.allclose(rotations @ rotations.transpose(-1, -2), torch.eye(3).expand_as(rotations), atol=1e-5)


def test_head_rotation_is_the_chain_product(builtin_rig):
    """Independent check with scipy: head = prod_j (rest_j @ R_j), relative to rest."""
    theta, *_ = random_inputs(builtin_rig, 4, seed=3, scale=0.6)
    head = builtin_rig.head_rotation(theta).double().numpy()
    local = builtin_rig.rest_local[:, :3, :3].double().numpy()
    for b in range(4):
        posed = np.eye(3)
        rest = np.eye(3)
        for j in range(8):
            posed = posed @ local[j] @ Rotation.from_rotvec(theta[b, j].double().numpy()).as_matrix()
            rest = rest @ local[j]
        np.testing.assert_allclose(head[b], posed @ rest.T, atol=1e-5)
    assert torch.allclose(builtin_rig.head_rotation(builtin_rig.neutral(2)), torch.eye(3).expand(2, 3, 3), atol=1e-6)


def test_positive_x_rotation_is_flexion_nose_goes_down(builtin_rig):
    nose = int(torch.argmax(builtin_rig.template[:, 2]))
    theta = builtin_rig.neutral(1)
    theta[0, :, 0] = 0.05  # flexion at every level
    moved = builtin_rig(theta, eta=torch.zeros(1))[0, nose] - builtin_rig.template[nose]
    assert moved[1] < -1.0  # the face goes down towards the chest
    theta = builtin_rig.neutral(1)
    theta[0, :, 1] = 0.1  # axial rotation towards the subject's left (+x)
    moved = builtin_rig(theta, eta=torch.zeros(1))[0, nose] - builtin_rig.template[nose]
    assert moved[0] > 1.0


@pytest.fixture(scope="module")
def builtin_rig64(builtin_rig):
    return HeadNeckModel(builtin_rig.rig).double()


def test_gradients_match_finite_differences(builtin_rig64):
    """float64 gradcheck in psi (6 of the 55 shapes, the others held at non-zero values: all share one
    product), eta, beta, the larynx map weights and theta, for 2 frames (so that a gradient leaking across
    frames shows).  The vertices are projected on 4 random unit directions (4 backward passes); tau is
    piecewise linear in the bilinear map (its own test below)."""
    g = torch.Generator().manual_seed(1)
    theta, psi, tau, eta, beta = (t.double() for t in random_inputs(builtin_rig64, 2, seed=1))
    weights = torch.tensor([[0.6, 0.3, 0.1], [0.2, 0.5, 0.3]], dtype=torch.float64)
    shapes = [EXPRESSION_NAMES.index(n) for n in ("jawOpen", "mouthSmile_L", "eyeBlink_R", "browInnerUp_L",
                                                  "cheekPuff_R", "mouthFunnel")]
    probe = torch.randn(4, builtin_rig64.num_vertices * 3, generator=g, dtype=torch.float64)
    probe = probe / probe.norm(dim=1, keepdim=True)

    def projected(subset, eta, beta, weights, theta):
        full = psi.index_copy(1, torch.tensor(shapes), subset)
        return probe @ builtin_rig64(theta, full, tau, eta, beta, larynx_weights=weights).reshape(2, -1).T

    inputs = tuple(t.clone().requires_grad_(True) for t in (psi[:, shapes], eta, beta, weights, theta))
    assert torch.autograd.gradcheck(projected, inputs, eps=1e-6, atol=1e-8, rtol=1e-6)


def test_tau_gradient_matches_finite_differences(builtin_rig):
    theta, psi, _, _, _ = random_inputs(builtin_rig, 1, seed=4)
    probe = torch.randn(1, builtin_rig.num_vertices, 3, generator=torch.Generator().manual_seed(5))
    tau = torch.tensor([0.0123], requires_grad=True)
    (builtin_rig(theta, psi, tau) * probe).sum().backward()
    h = 1e-4  # well inside one texel (1/255) so the bilinear map is linear over the step
    with torch.no_grad():
        difference = builtin_rig(theta, psi, tau.detach() + h) - builtin_rig(theta, psi, tau.detach() - h)
    numeric = float((difference * probe).sum()) / (2 * h)
    assert abs(float(tau.grad) - numeric) < 0.05 * abs(numeric)


def test_larynx_map_stack_is_weighted_by_identity(builtin_rig):
    tau = torch.tensor([0.01, 0.01])
    eta = torch.ones(2)
    mixed = builtin_rig.larynx_offsets(tau, eta, torch.tensor([[0.0, 1.0, 0.0], [0.5, 0.0, 0.5]]))
    single = [builtin_rig.larynx_offsets(tau[:1], eta[:1], torch.eye(3)[k:k + 1])[0] for k in range(3)]
    assert torch.allclose(mixed[0], single[1], atol=1e-6)
    assert torch.allclose(mixed[1], 0.5 * single[0] + 0.5 * single[2], atol=1e-6)
    assert not torch.allclose(single[0], single[1], atol=1e-3)


def test_pose_correctives_use_rotation_minus_identity_without_the_root(builtin_rig):
    rig = builtin_rig.rig
    n = rig.template.shape[0]
    basis = np.random.default_rng(0).normal(0, 0.01, (8 * 9, n * 3)).astype(np.float32)
    model = HeadNeckModel(dataclasses.replace(rig, pose_correctives=basis))
    theta = builtin_rig.neutral(1)
    theta[0, 0] = torch.tensor([0.3, 0.1, 0.0])  # the root's rotation has no corrective
    assert torch.allclose(model(theta), builtin_rig(theta), atol=1e-5)
    theta[0, 4] = torch.tensor([0.0, 0.2, 0.1])
    rotation = torch.tensor(Rotation.from_rotvec([0.0, 0.2, 0.1]).as_matrix(), dtype=torch.float32)
    features = torch.zeros(8, 9)
    features[4] = (rotation - torch.eye(3)).reshape(-1)
    expected_rest = model.template + (features.reshape(1, -1) @ torch.tensor(basis)).reshape(-1, 3)
    rest = model.rest_shape(rotations=model.rotations(theta), eta=torch.zeros(1))[0]
    assert torch.allclose(rest, expected_rest, atol=1e-5)


def test_rest_shape_takes_its_batch_from_the_inputs(builtin_rig):
    psi = torch.zeros(3, 55)
    psi[1, builtin_rig.expression_names.index("jawOpen")] = 1.0
    rest = builtin_rig.rest_shape(psi=psi)
    assert rest.shape == (3, builtin_rig.num_vertices, 3)
    alone = builtin_rig.rest_shape()  # no input: one frame, template plus the rest larynx
    assert alone.shape == (1, builtin_rig.num_vertices, 3)
    assert torch.allclose(rest[0], alone[0]) and torch.allclose(rest[2], alone[0])
    assert torch.allclose(rest[1] - rest[0], builtin_rig.expression_deltas[EXPRESSION_NAMES.index("jawOpen")],
                          atol=1e-5)


def test_turned_bone_frames_keep_the_geometry_and_change_the_axes(builtin_rig, turned_rig):
    """The conftest rig: the built-in rig with oc1 pointing into the face and c1c2 turned about y."""
    oc1, c1c2 = 7, 6
    assert float(turned_rig.rest_world[oc1, 2, 1]) > 0.95          # oc1's y axis points forward (+z), as the release's
    assert torch.allclose(turned_rig(turned_rig.neutral(1)), builtin_rig(builtin_rig.neutral(1)), atol=1e-5)
    # anatomical frames: the same in the world (the rest rotations), other axes in bone coordinates
    assert torch.allclose(turned_rig.anatomical_rest_rotations, builtin_rig.anatomical_rest_rotations, atol=1e-6)
    # oc1: flexion (anatomical +x, lateral) is about its bone x; axial rotation (anatomical +y, up the spine) is
    # about its bone -z (its y points forward, its z down).  c1c2's bone z points to the subject's left (+x):
    # its flexion is about its bone z.
    flexion, axial = torch.zeros(1, 8, 3), torch.zeros(1, 8, 3)
    flexion[..., 0], axial[..., 1] = 1.0, 1.0
    assert torch.equal(turned_rig.from_anatomical(flexion)[0, oc1], torch.tensor([1.0, 0.0, 0.0]))
    assert torch.equal(turned_rig.from_anatomical(axial)[0, oc1], torch.tensor([0.0, 0.0, -1.0]))
    assert torch.equal(turned_rig.from_anatomical(flexion)[0, c1c2], torch.tensor([0.0, 0.0, 1.0]))
    theta, *_ = random_inputs(builtin_rig, 4, seed=6)              # anatomical: bone = anatomical on the built-in rig
    bone = turned_rig.from_anatomical(theta)
    assert (bone - theta).abs().max() > 0.05                         # the conversion is not the identity ...
    assert torch.allclose(turned_rig.to_anatomical(bone), theta, atol=1e-6)
    assert torch.allclose(turned_rig(bone), builtin_rig(theta), atol=1e-4)  # ... and gives the same pose
    assert torch.allclose(turned_rig.head_rotation(bone), builtin_rig.head_rotation(theta), atol=1e-5)


def test_expressions_are_plausible(builtin_rig):
    deltas = builtin_rig.expression_deltas
    names = builtin_rig.expression_names
    template = builtin_rig.template
    chin_band = (template[:, 1] > -4.5) & (template[:, 1] < -2.5)
    chin = int(torch.argmax(torch.where(chin_band, template[:, 2], torch.tensor(-1e9))))
    assert deltas[names.index("jawOpen"), chin, 1] < -1.0
    blink_left = deltas[names.index("eyeBlink_L")]
    moved = blink_left.norm(dim=1) > 0.05
    assert (builtin_rig.template[moved, 0] > 0).all()  # the subject's left is +x
    assert blink_left[:, 1].min() < -0.5
    # _R shapes mirror _L shapes across x = 0.
    left, right = deltas[names.index("mouthSmile_L")], deltas[names.index("mouthSmile_R")]
    mirror = torch.tensor([-1.0, 1.0, 1.0])
    assert torch.allclose(left.sum(0) * mirror, right.sum(0), rtol=0.05, atol=0.05)
    assert (deltas.reshape(55, -1).abs().max(dim=1).values > 0.1).all()  # every shape does something


@pytest.mark.parametrize("bad, message", [
    (dict(theta=torch.zeros(2, 7, 3)), r"theta has shape \[2, 7, 3\], expected \[B,8,3\]"),
    (dict(psi=torch.zeros(2, 52)), r"psi has shape \[2, 52\], expected \[2,55\]"),
    (dict(tau=torch.zeros(3)), r"tau has shape \[3\], expected \[2\]"),
])
def test_wrong_input_shapes_are_named(builtin_rig, bad, message):
    kwargs = dict(theta=torch.zeros(2, 8, 3))
    kwargs.update(bad)
    with pytest.raises(ValueError, match=message):
        builtin_rig(**kwargs)


def _dense_reference(model: HeadNeckModel, theta, psi, tau, eta, beta) -> torch.Tensor:
    """The forward pass composed from the pure steps over the whole mesh: the rest shape with the larynx
    sampled at every larynx-region vertex, then one LBS (no chunks, threads or larynx selection)."""
    rest = model.rest_shape(psi=psi, tau=tau, eta=eta, beta=beta, rotations=model.rotations(theta))
    transforms = skinning_transforms(model.joint_transforms(theta), model.rest_world_inverse)
    return linear_blend_skinning(rest, model.skin_weights, transforms)


@pytest.mark.parametrize("threads", [1, 2])
def test_chunked_threaded_forward_equals_the_dense_composition(builtin_rig, threads):
    """Batches on 1 and 2 threads (several chunks each), taus from far below to far above the map (the larynx
    selection by tau range), and a batch mixing them."""
    theta, psi, _, eta, beta = random_inputs(builtin_rig, 16, seed=8)
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        for tau in (torch.full((16,), -0.4), torch.linspace(-0.08, 0.12, 16), torch.full((16,), 0.6),
                    torch.tensor([-1.0, 1.0] * 8), torch.zeros(16)):
            with torch.no_grad():
                posed = builtin_rig(theta, psi, tau, eta, beta)
                expected = _dense_reference(builtin_rig, theta, psi, tau, eta, beta)
            assert float((posed - expected).abs().max()) < 2e-5, tau
        assert torch.get_num_threads() == threads  # the caller's setting survives the pass
        seen = []
        worker = threading.Thread(target=lambda: seen.append(torch.get_num_threads()))
        worker.start()
        worker.join()
        assert seen == [threads]  # and new threads still start with it
    finally:
        torch.set_num_threads(before)


def test_larynx_selection_keeps_every_displaced_vertex(builtin_rig):
    """At each tau the vertices left out of the batch's larynx selection have exactly zero displacement."""
    taus = torch.linspace(-0.3, 0.3, 121)
    full = builtin_rig.larynx_region_offsets(taus, torch.ones(121)).norm(dim=-1)  # [T, M]
    for k in range(0, 121, 10):
        region, offsets = builtin_rig._larynx_active(taus[k:k + 1], torch.ones(1), None)
        inside = torch.isin(builtin_rig.larynx_vertices, region)
        assert float(full[k, ~inside].sum()) == 0.0
        assert int(inside.sum()) < len(builtin_rig.larynx_vertices)  # it does leave vertices out
        assert torch.allclose(offsets[:, 0].T, builtin_rig.larynx_region_offsets(
            taus[k:k + 1], torch.ones(1))[0, inside], atol=1e-7)


@pytest.mark.parametrize("skinning", ["lbs", "dqs"])
def test_backward_in_chunks_on_threads_matches_one_thread(builtin_rig, skinning):
    theta, psi, tau, eta, beta = random_inputs(builtin_rig, 12, seed=9)
    probe = torch.randn(12, builtin_rig.num_vertices, 3, generator=torch.Generator().manual_seed(10))
    before = torch.get_num_threads()
    results = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            inputs = [t.clone().requires_grad_(True) for t in (theta, psi, tau, eta, beta)]
            posed = builtin_rig(*inputs, skinning=skinning)
            (posed * probe).sum().backward()
            with torch.no_grad():
                fast = builtin_rig(theta, psi, tau, eta, beta, skinning=skinning)
            assert torch.equal(posed.detach(), fast)  # recording or not, the same pass
            results.append([t.grad for t in inputs])
    finally:
        torch.set_num_threads(before)
    for one, two in zip(*results):  # other chunk sizes: float32 sums in another order
        assert float((one - two).abs().max()) <= 1e-5 * float(one.abs().max())
        assert float(one.abs().max()) > 0


def test_empty_batch(builtin_rig):
    assert builtin_rig(torch.zeros(0, 8, 3)).shape == (0, builtin_rig.num_vertices, 3)


@pytest.mark.parametrize("skinning", ["lbs", "dqs"])
@pytest.mark.parametrize("batch, size, threads", [(1, None, 1), (3, 64, 1), (3, 64, 2), (16, 500, 2),
                                                  (16, None, 2), (40, 1000, 1), (5, 100000, 2)])
def test_engine_equals_the_reference_path(builtin_rig, skinning, batch, size, threads):
    """The chunked, threaded engine (``forward``) and ``pose_vertices`` (``pose_reference``, plain torch over the
    whole mesh) agree, with expressions, shapes, tau and eta, for chunk sizes from 64 vertices to the whole
    mesh and 1 or 2 threads."""
    from base.threads import single_thread

    theta, psi, tau, eta, beta = random_inputs(builtin_rig, batch, seed=batch, scale=1.0)
    tau = tau * 4  # up to +-0.2: the larynx selection leaves vertices out
    before = torch.get_num_threads()
    torch.set_num_threads(threads)
    try:
        with torch.no_grad(), single_thread():
            posed = builtin_rig._pose(theta, psi, tau, eta, beta, None, skinning, threads, size)
        with torch.no_grad():
            expected = builtin_rig.pose_reference(theta, psi, tau, eta, beta, skinning=skinning)
            default = builtin_rig(theta, psi, tau, eta, beta, skinning=skinning)
    finally:
        torch.set_num_threads(before)
    assert posed.shape == expected.shape == (batch, builtin_rig.num_vertices, 3)
    assert float((posed - expected).abs().max()) < 2e-5
    assert float((default - expected).abs().max()) < 2e-5
    assert float((expected - builtin_rig.template).abs().max()) > 1.0  # the inputs do move the mesh
