"""The in-vivo style of the prior (``data.prior.style=invivo``, the default): segmental shares and coupling
from measured in-vivo kinematics.  Angles and joint order: ``data.cervical_prior``.

Sources (each constant below names the one it comes from; "assumption" where the literature gave us none):

- [Z21] "In vivo primary and coupled segmental motions of the healthy female head-neck complex during dynamic
  head axial rotation", J Biomech 2021: dual fluoroscopy of C0-T1, 8 asymptomatic women, upright, dynamic.
  One-sided rotation 55.5 +- 10.8 deg; C0-C2 39.7 +- 9.6 deg (71.3 +- 8.5 %), C2-T1 10.0 +- 3.7 deg
  (18.6 +- 7.2 %); coupled bending upper contralateral 18.2 +- 5.9 deg, lower ipsilateral 21.4 +- 5.1 deg.
- [I04a] Ishii et al., "Kinematics of the upper cervical spine in rotation: in vivo three-dimensional
  analysis", Spine 29(7):E139-E144, 2004 (MRI, 15 volunteers, 15 deg steps): axial O-C1 1.7 +- 1.5, C1-C2
  36.2 +- 4.5 deg; C1-C2's increments shrink as the head turns further; coupled contralateral bending O-C1
  4.1, C1-C2 3.8 deg; coupled extension O-C1 13.3, C1-C2 6.9 deg (supine, at maximal rotation).
- [I04b] Ishii et al., "Kinematics of the subaxial cervical spine in rotation in vivo three-dimensional
  analysis", Spine 29(24):2826-2831, 2004: at maximal head rotation (69.5 deg) axial C2-C3 2.2, C3-C4 4.5,
  C4-C5 4.6, C5-C6 4.0, C6-C7 1.6, C7-T1 1.5 deg, coupled bending to the same side at every level.
- [S13] Salem et al., "In vivo three-dimensional kinematics of the cervical spine during maximal axial
  rotation", Man Ther 18(4):339-344, 2013 (CT, 20 volunteers): axial O-C1 2.5, C1-C2 37.5 deg, coupled
  contralateral bending O-C1 5.0, C1-C2 2.5 deg, extension O-C1 12.0, C1-C2 4.0 deg; coupled extension at
  C2-C3..C4-C5 and flexion at C5-C6, C6-C7.
- [W10] Wu, Kuo, Lan, Tsai, Su, "Segmental percentage contributions of cervical spine during different motion
  ranges of flexion and extension" (videofluoroscopy, 48 healthy adults; shares of C2-C7 motion): flexion's
  first third C3/4 29.89 %, C4/5 37.14 %, its middle to final thirds C5/6 22.57-29.45 %, C6/7 28.80-37.42 %;
  extension starts at C5/6 (30.21 %) and ends at C3/4 (27.55 %) and C4/5 (29.77 %).
- [A13] Anderst et al., Spine 2013 (PMC3686971; biplane radiography at 30 images/s, 18 asymptomatic
  subjects): C2/C3-C4/C5 contribute most in mid-range flexion-extension, C5/C6 and C6/C7 near its ends.
- [L14] Lan et al., "The shift of segmental contribution ratio in patients with herniated disc during cervical
  lateral bending", BMC Musculoskelet Disord 15:273, 2014: healthy C2/3..C6/7 lateral bending 7.66 +- 2.37,
  8.37 +- 2.11, 8.91 +- 3.22, 7.19 +- 2.29, 6.31 +- 2.11 deg.
- [WP90] / [P88]: the published segmental ranges of ``data.joint_limits.RANGES_DEG`` (White & Panjabi 1990;
  Panjabi et al. 1988), the rig's joint limits.
- [C06] Cook et al., J Manipulative Physiol Ther 29:570-575, 2006 (systematic review): below C2, bending and
  rotation couple to the same side in every 3D study; the upper cervical coupling direction varies.
- [BM00] Bogduk & Mercer, Clin Biomech 15:633-648, 2000 (review): nodding starts at the craniocervical junction.
- [FH85] Flash & Hogan, J Neurosci 5:1688-1703, 1985: minimum-jerk movements.


How the generator uses these tables: ``data.cervical_prior.generator``.
"""
from __future__ import annotations

import numpy as np

from data.joint_limits import JOINT_LEVELS, RANGES_DEG

NUM_JOINTS = len(JOINT_LEVELS)
SUBAXIAL = slice(0, 6)          # C7-T1 .. C2-C3
C6C7, C5C6, C1C2, OC1 = 1, 2, 6, 7
FLEX, EXT, LAT, AXIAL = range(4)  # columns of RANGES_DEG, and the four directions of the head
DIRECTIONS = ("flexion", "extension", "lateral", "axial")
SAGITTAL_DRIVE, AXIAL_DRIVE, LATERAL_DRIVE = range(3)
MOTION_KINDS = ("nod", "turn", "tilt", "combo")



def _normalised(x) -> np.ndarray:
    x = np.asarray(x, dtype=float)
    return x / x.sum()


def _start_shares(full: np.ndarray, fixed: dict[int, float]) -> np.ndarray:
    """Start shares: the levels in ``fixed`` take their given share, the others keep their proportions of ``full``."""
    start = full.copy()
    rest = [j for j in range(NUM_JOINTS) if j not in fixed]
    start[rest] = full[rest] * (1.0 - sum(fixed.values())) / full[rest].sum()
    for j, share in fixed.items():
        start[j] = share
    return start


# ----------------------------------------------------------------------------- shares (root to head)

# Axial rotation.  [Z21] regions normalised to their sum; O-C1 : C1-C2 = mean of [I04a] 1.7 : 36.2 and
# [S13] 2.5 : 37.5; the subaxial split of [I04b] (C7-T1 1.5, C6-C7 1.6, C5-C6 4.0, C4-C5 4.6, C3-C4 4.5, C2-C3 2.2).
UPPER_AXIAL_SHARE = 71.3 / (71.3 + 18.6)
_upper_axial = _normalised([(1.7 + 2.5) / 2, (36.2 + 37.5) / 2])      # O-C1, C1-C2
AXIAL_FULL = np.concatenate([(1 - UPPER_AXIAL_SHARE) * _normalised([1.5, 1.6, 4.0, 4.6, 4.5, 2.2]),
                             UPPER_AXIAL_SHARE * _upper_axial[::-1]])
C1C2_SMALL_YAW_SHARE = 0.90     # assumption, consistent with [I04a]
AXIAL_START = _start_shares(AXIAL_FULL, {C1C2: C1C2_SMALL_YAW_SHARE})

# Flexion.  Full range: the published flexion ranges [WP90, P88].  Start: see the module docstring.
FLEXION_FULL = _normalised(RANGES_DEG[:, FLEX])
_upper_flexion = 0.30 * _normalised(RANGES_DEG[[C1C2, OC1], FLEX])                      # [BM00]; value assumed
_c2c7_flexion_start = _normalised([0.11, 0.11, 0.3714, 0.2989, 0.11])  # C6/7, C5/6, C4/5, C3/4, C2/3 [W10]
FLEXION_START = np.concatenate([[0.02], (1 - 0.02 - 0.30) * _c2c7_flexion_start, _upper_flexion])

# Extension.  Full range: the published extension ranges.  Start: C5/6 30.21 % of C2-C7 [W10], the rest spread.
EXTENSION_FULL = _normalised(RANGES_DEG[:, EXT])
_upper_extension = 0.30 * _normalised(RANGES_DEG[[C1C2, OC1], EXT])
_c2c7_extension_start = _normalised([0.20, 0.3021, 0.20, 0.15, 0.1479])  # C6/7, C5/6, C4/5, C3/4, C2/3
EXTENSION_START = np.concatenate([[0.05], (1 - 0.05 - 0.30) * _c2c7_extension_start, _upper_extension])

# Lateral bending.  [L14] C2/3..C6/7 (listed here root first), published C7-T1, C1-C2, O-C1 [WP90].
LATERAL_FULL = _normalised([RANGES_DEG[0, LAT], 6.31, 7.19, 8.91, 8.37, 7.66, RANGES_DEG[C1C2, LAT],
                            RANGES_DEG[OC1, LAT]])
LATERAL_START = _start_shares(LATERAL_FULL, {C1C2: 0.5 * LATERAL_FULL[C1C2], OC1: 0.5 * LATERAL_FULL[OC1]})

FULL_SHARES = np.stack([FLEXION_FULL, EXTENSION_FULL, LATERAL_FULL, AXIAL_FULL])      # [4 directions, J]
START_SHARES = np.stack([FLEXION_START, EXTENSION_START, LATERAL_START, AXIAL_START])

# Head range in a direction = this times the sum of the published segmental ranges: [Z21]'s 55.5 deg of
# one-sided C0-T1 rotation over the 77 deg sum of the published one-sided axial ranges; the same ratio is
# assumed for flexion, extension and lateral bending (no C0-T1 in-vivo totals found for them).
HEAD_RANGE_UTILISATION = 55.5 / RANGES_DEG[:, AXIAL].sum()
HEAD_RANGE_DEG = HEAD_RANGE_UTILISATION * RANGES_DEG.sum(0)   # [4]: the default person's head range per direction

# ----------------------------------------------------------------------------- coupling

# Per-level distributions of each coupled motion (sum 1 over the levels that take part).
_subaxial_rotation = np.concatenate([_normalised([1.5, 1.6, 4.0, 4.6, 4.5, 2.2]), [0.0, 0.0]])   # [I04b]
_upper_bending = np.array([0, 0, 0, 0, 0, 0, 3.8, 4.1]) / (3.8 + 4.1)                            # [I04a]
COUPLING = {
    # degrees of coupled motion per degree of the head's primary angle
    "upper_contralateral_bending_per_rotation": 18.2 / 55.5,   # [Z21]
    "lower_ipsilateral_bending_per_rotation": 21.4 / 55.5,     # [Z21]
    "oc1_extension_per_rotation": 0.08,                        # assumption (see the module docstring)
    "c1c2_extension_per_rotation": 0.04,                       # assumption
    "subaxial_rotation_per_bending": 10.0 / 21.4,              # [Z21] lower region, assumed reversible
    "c1c2_counter_rotation_in_bending": 0.8,                   # assumption
}
LOWER_BENDING_LEVELS = _subaxial_rotation                       # assumption: as the subaxial rotation
UPPER_BENDING_LEVELS = _upper_bending
BALANCING_FLEXION_LEVELS = np.array([0, 0.5, 0.5, 0, 0, 0, 0, 0])  # C6-C7, C5-C6 [S13]; halves assumed
SUBAXIAL_BENDING_LEVELS = np.concatenate([np.ones(6), [0.0, 0.0]])
SATURATION_POWER = 8
SOFT_ABS_DEG = 10.0
