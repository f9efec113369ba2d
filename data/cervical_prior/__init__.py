"""Prior of cervical motion: seeded synthetic theta sequences in one of two styles, and the loader of real ones.

HACK drives its 8 cervical joints from one head orientation; without motion capture of the spine we learn
that mapping from this generator.  Angles are Euler angles per joint in its anatomical frame
(``HeadNeckModel.to_anatomical``; the rig takes ``rig.from_anatomical(theta)``), ``R = Rz(az) Ry(ay) Rx(ax)``
(``base.rotations``): ``ax`` flexion +, ``ay`` axial rotation + to the subject's left, ``az`` lateral bending
+ to the subject's right; joints root to head (``data.joint_limits.JOINT_LEVELS``: C7-T1 ... O-C1).  Head
orientation follows by forward kinematics (``HeadNeckModel.head_rotation``).

Modules:
- ``invivo``: the default style (``PriorConfig.style="invivo"``, ``data.prior.style=invivo``): segmental shares
  and coupling from measured in-vivo kinematics, each constant cited;
- ``hack``: HACK's own fitted style (``style="hack"``): half the axial rotation at C1-C2, the rest and every
  other direction nearly even, C7-T1 barely moving, no coupling;
- ``generator``: :class:`PriorConfig`, persons, the segmental model, :func:`sample_sequences`;
- ``drives``: the smooth drives (nods, turns, tilts, combinations);
- ``real``: :func:`load_theta_sequences`, real HACK-layout theta arrays.
"""
from data.cervical_prior.generator import (
    PriorConfig,
    head_rotations,
    sample_persons,
    sample_sequences,
    segmental_euler,
)
from data.cervical_prior.invivo import (
    AXIAL,
    C1C2,
    EXT,
    FLEX,
    FULL_SHARES,
    HEAD_RANGE_DEG,
    LAT,
    MOTION_KINDS,
    OC1,
    START_SHARES,
)
from data.cervical_prior.real import load_theta_sequences

__all__ = ["AXIAL", "C1C2", "EXT", "FLEX", "FULL_SHARES", "HEAD_RANGE_DEG", "LAT", "MOTION_KINDS", "OC1",
           "START_SHARES", "PriorConfig", "head_rotations", "load_theta_sequences", "sample_persons",
           "sample_sequences", "segmental_euler"]
