"""The HACK style of the prior (``data.prior.style=hack``): the segmental shares of HACK's own fitted theta
sequences, for users who animate HACK and expect its motion rather than the in-vivo one.

HACK fits its thetas with the paper's E_sim (adjacent joints alike, ``data.joint_limits.adjacent_similarity_
energy``) and E_rot (the limits) with the head orientation exact.  In its sequences (issue 46, measured on a
real HACK theta sequence this repository does not hold): about half of the head's axial rotation sits at
C1-C2 and the rest spreads nearly evenly over C2-C7; flexion-extension spreads nearly evenly over the levels
including O-C1, lateral bending likewise; C7-T1 barely moves.  The tables below write that down:

- every direction: C7-T1 2 % ("barely moves"; the value is an assumption);
- axial rotation: C1-C2 50 %, O-C1 3 % (assumption: its published axial range, 5 deg, is small), the other
  45 % evenly over C2-C3 .. C6-C7 (9 % each);
- flexion, extension, lateral bending: the other 98 % evenly over the seven levels C6-C7 .. O-C1 (14 % each).

The shares do not change with the size of the motion (start = end: E_sim and E_rot have no term that would
make them), and nothing couples: the coupling ratios are zero (E_sim and E_rot spread the head's rotation,
they add none).  Everything else (persons' ranges and their saturation, drives, share jitter) is the
generator's (``data.cervical_prior.generator``), so every pose stays inside the published limits, as E_rot
asks of HACK's fits; near a limit a level saturates and the head moves less.
"""
from __future__ import annotations

import numpy as np

from data.cervical_prior.invivo import COUPLING, NUM_JOINTS

C7T1_SHARE = 0.02                   # "c7t1 barely moves" (issue 46); value assumed
C1C2_AXIAL_SHARE = 0.50             # "about half of the head's axial rotation" (issue 46)
OC1_AXIAL_SHARE = 0.03              # assumption (O-C1's published axial range is 5 deg)

_even = np.full(NUM_JOINTS, (1.0 - C7T1_SHARE) / (NUM_JOINTS - 1))
_even[0] = C7T1_SHARE
_axial = np.concatenate([[C7T1_SHARE],
                         np.full(5, (1.0 - C7T1_SHARE - C1C2_AXIAL_SHARE - OC1_AXIAL_SHARE) / 5),
                         [C1C2_AXIAL_SHARE, OC1_AXIAL_SHARE]])
HACK_SHARES = np.stack([_even, _even, _even, _axial])          # [4 directions (FLEX, EXT, LAT, AXIAL), J]
HACK_COUPLING = np.zeros(len(COUPLING))                          # in ``COUPLING`` order: none
