"""Anatomical joint limits, the E_rot and E_sim priors, and the clamp."""
from __future__ import annotations

import math

import torch

from base.rotations import axis_angle_to_euler, euler_to_axis_angle, euler_to_matrix, matrix_to_euler
from data.joint_limits import (
    adjacent_similarity_energy,
    clamp_to_limits,
    euler_limits,
    range_of_motion_shares,
    rotation_limit_energy,
    within_limits,
)


def random_euler_inside(batch: int, seed: int, fraction: float = 0.9) -> torch.Tensor:
    lower, upper = euler_limits()
    u = torch.rand(batch, 8, 3, generator=torch.Generator().manual_seed(seed))
    return lower * fraction + (upper - lower) * fraction * u


def test_euler_convention_is_rz_ry_rx():
    angles = torch.tensor([[0.3, -0.2, 0.1]])
    rx = torch.tensor([[1, 0, 0], [0, math.cos(0.3), -math.sin(0.3)], [0, math.sin(0.3), math.cos(0.3)]])
    ry = torch.tensor([[math.cos(-0.2), 0, math.sin(-0.2)], [0, 1, 0], [-math.sin(-0.2), 0, math.cos(-0.2)]])
    rz = torch.tensor([[math.cos(0.1), -math.sin(0.1), 0], [math.sin(0.1), math.cos(0.1), 0], [0, 0, 1]])
    assert torch.allclose(euler_to_matrix(angles)[0], rz @ ry @ rx, atol=1e-6)
    assert torch.allclose(matrix_to_euler(rz @ ry @ rx)[None], angles, atol=1e-6)


def test_published_shares_c1c2_holds_half_of_axial_rotation():
    share, extension_share = range_of_motion_shares()
    assert torch.allclose(share.sum(0), torch.ones(3)) and torch.allclose(extension_share.sum(0), torch.ones(3))
    assert 0.45 < share[6, 1] < 0.6  # C1-C2: about half of cervical axial rotation
    assert share[6, 1] == share[:, 1].max()
    assert extension_share[7, 0] == extension_share[:, 0].max()  # O-C1 extends most (Panjabi 1988: 21 deg)


def test_rotation_energy_is_zero_inside_and_quadratic_outside():
    inside = euler_to_axis_angle(random_euler_inside(64, 0))
    assert rotation_limit_energy(inside).abs().max() < 1e-8
    _, upper = euler_limits()
    euler = torch.zeros(1, 8, 3)
    euler[0, 6, 0] = upper[6, 0] + 0.1  # C1-C2 flexed 0.1 rad past its limit
    assert abs(float(rotation_limit_energy(euler_to_axis_angle(euler))) - 0.01) < 1e-4


def test_similarity_energy_sums_adjacent_squared_differences():
    theta = torch.zeros(2, 8, 3)
    theta[0] = 0.2  # all joints equal: no penalty
    theta[1, 3, 0] = 0.1  # one joint differs from both neighbours
    energy = adjacent_similarity_energy(theta)
    assert energy[0].abs() < 1e-9 and abs(float(energy[1]) - 2 * 0.01) < 1e-7


def test_clamp_lands_inside_and_leaves_inside_alone():
    inside = euler_to_axis_angle(random_euler_inside(32, 1))
    assert torch.allclose(clamp_to_limits(inside), inside, atol=1e-5)
    wild = (torch.rand(32, 8, 3, generator=torch.Generator().manual_seed(2)) - 0.5) * 2.0
    clamped = clamp_to_limits(wild)
    assert not within_limits(wild).all()
    assert within_limits(clamped).all()
    assert torch.allclose(clamp_to_limits(clamped), clamped, atol=1e-5)
    lower, upper = euler_limits()
    euler = axis_angle_to_euler(clamped)
    on_bound = ((euler - upper).abs() < 1e-4) | ((euler - lower).abs() < 1e-4)
    assert on_bound.any()
