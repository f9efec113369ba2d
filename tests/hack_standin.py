"""A stand-in for a HACK-fitted theta sequence (issue 46), written apart from ``data.cervical_prior.hack``.

HACK fits its thetas with the paper's E_sim (adjacent joints alike) and E_rot (the limits) with the head
orientation exact; in its sequences about half of the head's axial rotation sits at C1-C2 and C7-T1 barely
moves (issue 46).  :func:`solve_hack_style` solves, per frame, for the joints of a given head orientation::

    min  W_HEAD |H(theta) - H*|^2 + E_sim'(theta) + W_ROT E_rot(theta)
         + W_SHARE (ay_C1C2 - share * sum_j ay_j)^2 + W_ROOT |theta_C7T1|^2 + W_RIDGE |theta|^2

E_sim' is E_sim (``data.joint_limits.adjacent_similarity_energy``, written out on a chain) without C1-C2's
axial component and without the C7-T1 / C6-C7 pair: HACK's C1-C2 turns apart from its neighbours and C7-T1
barely moves while the levels above it share evenly (issue 46), which E_sim on every component cannot give
(solved with it, O-C1 takes 23 % of the axial rotation and the subaxial levels a ramp from 3 to 14 %; with
the C7-T1 pair kept, flexion ramps from 6 % at C6-C7 to 17 % at C2-C3).  The share term places C1-C2, the
root term holds C7-T1, and a small ridge (W_RIDGE) decides what E_sim' leaves free.  L-BFGS on the joints'
Euler angles, all frames at once (they do not interact), then the exact correction
(``models.head2neck.correct_to_head``) removes the last head residual.  No share table is given for the other
levels or directions: E_sim spreads them.  :func:`hack_standin` applies it to the head orientations of
``test_head2neck.standin_recording`` (a session of turns, nods and tilts from a generator other than the
prior's), so neither the heads nor the joints come from the generator a model trains on.
"""
from __future__ import annotations

import torch

from base.rotations import euler_to_axis_angle, matrix_to_axis_angle
from data.cervical_prior import head_rotations
from data.joint_limits import rotation_limit_energy
from models.head2neck import chain_head_rotation, correct_to_head

W_HEAD, W_ROT, W_SHARE, W_ROOT, W_RIDGE = 1.0e3, 1.0e2, 10.0, 10.0, 1.0e-2
C1C2, C7T1 = 6, 0
# E_sim' weights per adjacent pair (row j: joint j + 1 against joint j) and component: C1-C2's axial (y) and
# the C7-T1 pair left out.
SIM_MASK = torch.ones(7, 3, dtype=torch.float64)
SIM_MASK[[C1C2 - 1, C1C2], 1] = 0.0
SIM_MASK[C7T1] = 0.0


def solve_hack_style(head: torch.Tensor, rig, share: float = 0.5, steps: int = 60) -> torch.Tensor:
    """Anatomical theta [F,8,3] giving the head orientations ``head`` [F,3,3] exactly, in HACK's style."""
    if list(rig.parents) != list(range(-1, len(rig.parents) - 1)):
        raise ValueError(f"a chain of joints expected, got parents {rig.parents}")
    head = head.double()
    rest = rig.anatomical_rest_rotations.double()
    v = matrix_to_axis_angle(head)                                          # [F,3] world rotation vector
    start = torch.einsum("jkc,fk->fjc", rest, v) / rest.shape[0]           # uniform split: a start point
    euler = start.clone().requires_grad_(True)                              # small angles: axis-angle ~ Euler
    optimiser = torch.optim.LBFGS([euler], lr=1.0, max_iter=steps, line_search_fn="strong_wolfe",
                                  tolerance_grad=1e-12, tolerance_change=1e-14, history_size=20)
    rig64 = _Rig64(rig)

    def objective() -> torch.Tensor:
        optimiser.zero_grad()
        theta = euler_to_axis_angle(euler)
        mismatch = ((chain_head_rotation(theta, rig64) - head) ** 2).sum((-1, -2))
        axial = euler[..., 1]
        share_term = (axial[:, C1C2] - share * axial.sum(-1)) ** 2
        similarity = (SIM_MASK * (theta[:, 1:] - theta[:, :-1]) ** 2).sum((1, 2))
        loss = (W_HEAD * mismatch + similarity + W_ROT * rotation_limit_energy(theta) + W_SHARE * share_term
                + W_ROOT * (theta[:, C7T1] ** 2).sum(-1) + W_RIDGE * (theta**2).sum((1, 2))).sum()
        loss.backward()
        return loss

    for _ in range(5):
        optimiser.step(objective)
    theta = euler_to_axis_angle(euler.detach()).float()
    return correct_to_head(theta, head.float(), rig)


class _Rig64:
    """The rig's parents and anatomical rest rotations in float64 (what ``chain_head_rotation`` reads)."""

    def __init__(self, rig):
        self.parents = rig.parents
        self.anatomical_rest_rotations = rig.anatomical_rest_rotations.double()


def hack_standin(rig, seed: int = 0, share: float = 0.5) -> torch.Tensor:
    """Anatomical theta [500,8,3]: the heads of ``standin_recording(seed)``, solved in HACK's style."""
    from test_head2neck import standin_recording

    return solve_hack_style(head_rotations(rig, standin_recording(seed)), rig, share)
