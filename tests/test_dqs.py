"""Dual-quaternion skinning (``models.rig.dual_quaternion_skinning``, ``HeadNeckModel(..., skinning="dqs")``):
volume under twist, agreement with LBS for rigid bindings, antipodal quaternions, gradients."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from base.rotations import axis_angle_to_matrix
from models.rig import HeadNeckModel, dual_quaternion_skinning, linear_blend_skinning

TWIST = np.radians(60.0)


def closed_volume(vertices: torch.Tensor, triangles: torch.Tensor) -> torch.Tensor:
    """Signed volume [B] of closed triangle meshes vertices [B,N,3] (divergence theorem)."""
    a, b, c = (vertices[:, triangles[:, k]] for k in range(3))
    return (a * torch.cross(b, c, dim=-1)).sum(-1).sum(1) / 6.0


def total_length(vertices: torch.Tensor, edges: torch.Tensor) -> torch.Tensor:
    return (vertices[:, edges[:, 0]] - vertices[:, edges[:, 1]]).norm(dim=-1).sum(1)


def cylinder(rings: int = 41, around: int = 32, length: float = 24.0, radius: float = 2.0):
    """A closed cylinder along y from 0 to ``length``: vertices [N,3], triangles [F,3] (outward), and its
    circumferential edges [E,2] (the ones a twist must not shorten)."""
    heights = np.linspace(0.0, length, rings)
    phi = np.linspace(0.0, 2 * np.pi, around, endpoint=False)
    grid = np.stack([radius * np.cos(phi)[None].repeat(rings, 0), heights[:, None].repeat(around, 1),
                     radius * np.sin(phi)[None].repeat(rings, 0)], -1).reshape(-1, 3)
    vertices = np.concatenate([grid, [[0.0, 0.0, 0.0], [0.0, length, 0.0]]])
    index = np.arange(rings * around).reshape(rings, around)
    nxt = np.roll(index, -1, axis=1)
    quads = np.stack([index[:-1], nxt[:-1], nxt[1:], index[1:]], -1).reshape(-1, 4)
    bottom, top = len(vertices) - 2, len(vertices) - 1
    triangles = np.concatenate([quads[:, [0, 2, 1]], quads[:, [0, 3, 2]],
                                np.stack([np.full(around, bottom), index[0], nxt[0]], -1),
                                np.stack([np.full(around, top), nxt[-1], index[-1]], -1)])
    circumferential = np.stack([index.reshape(-1), nxt.reshape(-1)], -1)
    return (torch.tensor(vertices), torch.tensor(triangles), torch.tensor(circumferential))


def chain_weights(heights: torch.Tensor, joint_heights: torch.Tensor, width: float) -> torch.Tensor:
    """Smooth weights [N,J]: Gaussians in height around each joint's segment centre, normalised."""
    centres = joint_heights + 0.5 * torch.diff(joint_heights, append=joint_heights[-1:] + width)
    weights = torch.exp(-0.5 * ((heights[:, None] - centres[None]) / width) ** 2)
    return weights / weights.sum(1, keepdim=True)


def twist_transforms(joint_heights: torch.Tensor, total: float) -> torch.Tensor:
    """[1,J,3,4] rest-to-posed transforms of a straight chain along y twisted about its axis by ``total``
    radians spread evenly over the joints: bone j turns by (j + 1) total / J, about the axis through its
    origin (on the y axis, so the rotation fixes it: t = 0)."""
    joints = len(joint_heights)
    angles = total * torch.arange(1, joints + 1, dtype=torch.float64) / joints
    rotations = torch.tensor(Rotation.from_rotvec(np.outer(angles.numpy(), [0.0, 1.0, 0.0])).as_matrix())
    return torch.cat([rotations, torch.zeros(joints, 3, 1, dtype=torch.float64)], -1)[None]


def test_twisted_cylinder_keeps_volume_and_girth_with_dqs_not_with_lbs():
    vertices, triangles, circumferential = cylinder()
    joint_heights = torch.linspace(0.0, 21.0, 8, dtype=torch.float64)
    weights = chain_weights(vertices[:, 1], joint_heights, width=3.0)
    transforms = twist_transforms(joint_heights, TWIST)
    lbs = linear_blend_skinning(vertices[None], weights, transforms)
    dqs = dual_quaternion_skinning(vertices[None], weights, transforms)
    v0 = closed_volume(vertices[None], triangles)
    g0 = total_length(vertices[None], circumferential)
    assert float(v0) == pytest.approx(np.pi * 2.0**2 * 24.0, rel=0.01)  # a closed, outward mesh
    losses = {name: (float(1 - closed_volume(p, triangles) / v0), float(1 - total_length(p, circumferential) / g0))
              for name, p in (("lbs", lbs), ("dqs", dqs))}
    assert losses["lbs"][0] > 2e-3 and losses["lbs"][1] > 1e-3     # LBS collapses the twisted cylinder ...
    assert abs(losses["dqs"][0]) <= 0.5 * losses["lbs"][0]          # ... DQS keeps it (a rigid turn per vertex)
    assert abs(losses["dqs"][1]) <= 0.5 * losses["lbs"][1]
    assert abs(losses["dqs"][1]) < 1e-9  # the rings keep their girth exactly (the volume moves only by the
    # twisted quads' diagonals)
    # each DQS vertex stays at its radius and height (a rotation about the axis); LBS pulls it inwards
    radius = dqs[0, :-2, [0, 2]].norm(dim=-1)
    assert torch.allclose(radius, torch.full_like(radius, 2.0), atol=1e-9)
    assert torch.allclose(dqs[0, :, 1], vertices[:, 1], atol=1e-9)
    assert float(lbs[0, :-2, [0, 2]].norm(dim=-1).min()) < 2.0 - 1e-3


def _ring_edges(rig: HeadNeckModel) -> torch.Tensor:
    """Edges joining two vertices at the same rest height: the built-in rig's rings (circumferential)."""
    edges = torch.cat([rig.faces[:, [0, 1]], rig.faces[:, [1, 2]], rig.faces[:, [2, 0]]])
    y = rig.template[:, 1]
    return edges[(y[edges[:, 0]] - y[edges[:, 1]]).abs() < 1e-5]


def _closed_neck_volume(vertices: torch.Tensor, rig: HeadNeckModel) -> torch.Tensor:
    """The built-in surface is open at the neck's base ring (the lowest vertices): close it with a fan to the
    ring's centroid, then the divergence-theorem volume [B]."""
    base = torch.nonzero(rig.template[:, 1] < float(rig.template[:, 1].min()) + 1e-5)[:, 0]
    order = base[torch.argsort(torch.atan2(rig.template[base, 0], -rig.template[base, 2]))]
    centre = vertices[:, base].mean(1, keepdim=True)
    closed = torch.cat([vertices, centre], 1)
    apex = torch.full_like(order, vertices.shape[1])
    fan = torch.stack([apex, order, torch.roll(order, -1)], -1)
    triangles = torch.cat([rig.faces, fan])
    volume = closed_volume(closed, triangles)
    return volume if float(volume[0]) > 0 else -volume  # the fan's orientation follows the surface's


def test_builtin_neck_twisted_60_degrees_keeps_its_volume_with_dqs(builtin_rig):
    """60 degrees of axial twist spread over the seven neck joints (c7t1 ... c1c2), anatomical +y."""
    anatomical = torch.zeros(1, 8, 3)
    anatomical[0, :7, 1] = TWIST / 7
    theta = builtin_rig.from_anatomical(anatomical)
    rings = _ring_edges(builtin_rig)
    assert len(rings) > 5000
    with torch.no_grad():
        rest = builtin_rig(builtin_rig.neutral(1), eta=torch.zeros(1))
        posed = {name: builtin_rig(theta, eta=torch.zeros(1), skinning=name) for name in ("lbs", "dqs")}
    v0, g0 = _closed_neck_volume(rest, builtin_rig), total_length(rest, rings)
    assert float(v0) > 1000.0  # cm^3: a closed head and neck
    losses = {name: (float(1 - _closed_neck_volume(p, builtin_rig) / v0), float(1 - total_length(p, rings) / g0))
              for name, p in posed.items()}
    assert losses["lbs"][0] > 2e-3 and losses["lbs"][1] > 5e-4
    assert abs(losses["dqs"][0]) <= 0.5 * losses["lbs"][0]
    assert abs(losses["dqs"][1]) <= 0.5 * losses["lbs"][1]
    # the head still turns by the full 60 degrees: both skinnings move the rigid head alike
    nose = int(torch.argmax(builtin_rig.template[:, 2]))
    assert torch.allclose(posed["lbs"][0, nose], posed["dqs"][0, nose], atol=1e-3)


def _one_hot(rig):
    weights = rig.skin_weights
    return np.eye(weights.shape[1], dtype=weights.dtype)[weights.argmax(1)]


def test_dqs_equals_lbs_for_one_hot_weights(builtin_rig):
    rigid = HeadNeckModel(dataclasses.replace(builtin_rig.rig, skin_weights=_one_hot(builtin_rig.rig)))
    g = torch.Generator().manual_seed(3)
    theta = (torch.rand(5, 8, 3, generator=g) - 0.5) * 1.6  # up to ~0.7 rad per joint and axis
    psi = torch.rand(5, 55, generator=g)
    tau = (torch.rand(5, generator=g) - 0.5) * 0.1
    with torch.no_grad():
        lbs = rigid(theta, psi, tau, skinning="lbs")
        dqs = rigid(theta, psi, tau, skinning="dqs")
        smooth = builtin_rig(theta, psi, tau, skinning="dqs")
    assert float((lbs - dqs).abs().max()) < 1e-4  # cm
    assert float((smooth - dqs).abs().max()) > 0.1  # the test is not vacuous: smooth weights differ


def test_pure_function_one_hot_matches_the_rigid_transforms_of_large_rotations():
    g = torch.Generator().manual_seed(4)
    joints, batch = 5, 3
    rotations = torch.tensor(Rotation.random(batch * joints, random_state=5).as_matrix()).reshape(batch, joints, 3, 3)
    transforms = torch.cat([rotations, torch.randn(batch, joints, 3, 1, generator=g, dtype=torch.float64)], -1)
    assignment = torch.randint(0, joints, (40,), generator=g)
    weights = torch.eye(joints, dtype=torch.float64)[assignment]
    rest = torch.randn(batch, 40, 3, generator=g, dtype=torch.float64)
    expected = torch.einsum("bnij,bnj->bni", rotations[:, assignment], rest) + transforms[:, assignment, :, 3]
    assert torch.allclose(dual_quaternion_skinning(rest, weights, transforms), expected, atol=1e-10)
    assert torch.allclose(linear_blend_skinning(rest, weights, transforms), expected, atol=1e-10)


def test_antipodal_quaternions_are_blended_the_short_way():
    """Bones turned +170 and -170 degrees about y: their quaternions lie in opposite hemispheres.  Blended
    half and half the short way (through 180 degrees), the point (1, 0, 0) goes to (-1, 0, 0); blended
    without the sign alignment it would come back to (1, 0, 0) (the identity)."""
    rotations = torch.tensor(Rotation.from_rotvec([[0, np.radians(170), 0], [0, -np.radians(170), 0]]).as_matrix())
    transforms = torch.cat([rotations, torch.zeros(2, 3, 1, dtype=torch.float64)], -1)[None]
    rest = torch.tensor([[[1.0, 0.0, 0.0]]], dtype=torch.float64)
    for weights in ([0.5, 0.5], [0.6, 0.4], [0.4, 0.6]):
        w = torch.tensor([weights], dtype=torch.float64)
        posed = dual_quaternion_skinning(rest, w, transforms)[0, 0]
        # on the short arc from +170 through 180 to -170 (= 190) degrees; quaternion blending is nlerp, within
        # 1e-3 rad of the proportional angle over a 20-degree arc
        angle = np.radians(170) * weights[0] + np.radians(190) * weights[1]
        turned = Rotation.from_rotvec([0, angle, 0]).apply([1.0, 0.0, 0.0])
        assert np.allclose(posed.numpy(), turned, atol=1e-3 if weights[0] != 0.5 else 1e-9), weights
        assert float(posed.norm()) == pytest.approx(1.0, abs=1e-9)


def test_dqs_gradients_match_finite_differences(builtin_rig):
    """float64 gradcheck (fast mode: random input and output directions) through the model with dual
    quaternions: theta, psi and the larynx size."""
    rig = HeadNeckModel(builtin_rig.rig, skinning="dqs").double()
    g = torch.Generator().manual_seed(6)
    theta = ((torch.rand(2, 8, 3, generator=g) - 0.5) * 0.6).double().requires_grad_(True)
    psi = torch.rand(2, 55, generator=g).double().requires_grad_(True)
    eta = torch.rand(2, generator=g).double().requires_grad_(True)
    tau = torch.tensor([0.01, -0.02], dtype=torch.float64)
    probe = torch.randn(6, rig.num_vertices * 3, generator=g).double()

    def projected(theta, psi, eta):
        return probe @ rig(theta, psi, tau, eta).reshape(2, -1).T  # [6, 2]

    assert torch.autograd.gradcheck(projected, (theta, psi, eta), eps=1e-6, atol=1e-6, rtol=1e-5, fast_mode=True)


def test_pure_dqs_gradients_in_rest_and_pose():
    g = torch.Generator().manual_seed(7)
    joints = 4
    heights = torch.linspace(0.0, 6.0, 12, dtype=torch.float64)
    weights = chain_weights(heights, torch.linspace(0.0, 4.5, joints, dtype=torch.float64), width=1.0)
    rest = torch.randn(1, 12, 3, generator=g, dtype=torch.float64).requires_grad_(True)
    axis_angle = (torch.randn(1, joints, 3, generator=g, dtype=torch.float64) * 0.5).requires_grad_(True)
    translation = torch.randn(1, joints, 3, 1, generator=g, dtype=torch.float64).requires_grad_(True)

    def skin(rest, axis_angle, translation):
        transforms = torch.cat([axis_angle_to_matrix(axis_angle), translation], -1)
        return dual_quaternion_skinning(rest, weights, transforms)

    assert torch.autograd.gradcheck(skin, (rest, axis_angle, translation), eps=1e-6, atol=1e-6)


def test_unknown_skinning_is_named(builtin_rig):
    with pytest.raises(ValueError, match=r"skinning='cubic': expected one of lbs, dqs"):
        builtin_rig(builtin_rig.neutral(1), skinning="cubic")
    with pytest.raises(ValueError, match="skinning='lbx'"):
        HeadNeckModel(builtin_rig.rig, skinning="lbx")
