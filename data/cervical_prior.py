"""Prior of cervical motion built on measured in-vivo kinematics: seeded synthetic theta sequences, and the
loader of real ones.

HACK drives its 8 cervical joints from one head orientation; without motion capture of the spine we learn
that mapping from this generator.  Angles are Euler angles per joint in its anatomical frame
(``HeadNeckModel.to_anatomical``; the rig takes ``rig.from_anatomical(theta)``), ``R = Rz(az) Ry(ay) Rx(ax)``
(``base.rotations``): ``ax`` flexion +, ``ay`` axial rotation + to the subject's left, ``az`` lateral bending
+ to the subject's right; joints root to head (``data.joint_limits.JOINT_LEVELS``: C7-T1 ... O-C1).  Head
orientation follows by forward kinematics (``HeadNeckModel.head_rotation``).

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

Generating process
------------------
1. A *person*.  Segmental ranges (the envelope, never exceeded): the published ranges [WP90] times
   ``clip(LogNormal(log 0.85, 0.2), 0.5, 1)`` per level and motion; the spread is [L14]'s coefficient of
   variation (0.25-0.36, partly measurement error, hence 0.2), the median 0.85 an assumption (a person moves
   inside the envelope).  Head range per direction (flexion, extension, lateral bending and axial rotation
   to one side): ``HEAD_RANGE_UTILISATION`` times the sum of the published segmental ranges, times
   ``LogNormal(0, 0.19)`` ([Z21]'s 10.8 / 55.5).  Shares and coupling ratios vary per person (below).
2. Three smooth *drives* per sequence in [-1, 1]: sagittal (+ flexion), axial (+ to the left), lateral
   (+ to the right): the fraction of the person's head range the movement asks for; nods, turns, tilts and
   combinations from minimum-jerk moves between held targets [FH85] and enveloped oscillations.
3. *Shares that depend on direction and size*.  For a drive of size m, level j moves
   ``T * (s0_j m + (s1_j - s0_j) m^2 / 2)``: its share of each further degree of head motion goes linearly
   from ``s0`` (start) to ``s1`` (end of the range), both summing to 1 over the levels, so the head moves
   ``T m`` and level j's share of a motion of size m is ``s0_j + (s1_j - s0_j) m / 2``.  We set the share at
   full range F (``(s0 + s1) / 2``) and the start share s0 from the sources; ``s1 = 2 F - s0``.
   - Axial rotation: F from [Z21] (C0-C2 71.3 %, C2-T1 18.6 %, normalised to their sum, as the means over
     subjects do not add to 100), O-C1 : C1-C2 from [I04a] and [S13] (means 2.1 : 36.85 deg), the subaxial
     split from [I04b].  Start: C1-C2 takes 90 % of a small yaw (assumption, consistent with [I04a]'s
     shrinking C1-C2 increments; the others keep their proportions), so its share falls from 0.90 to 0.75.
   - Flexion: F is the published flexion split [WP90, P88] (the ranges are measured at full flexion).  Start:
     O-C1 and C1-C2 30 % together [BM00] (in their published proportion; the value is an assumption), C7-T1
     2 % (assumption), C2-C7 the rest split as [W10]'s first third (C3/4 29.89 %, C4/5 37.14 %, the other
     33 % evenly: assumption); so flexion spreads down the neck as it grows (C5/6 and C6/7 take most of the
     end, as [W10] and [A13] report).
   - Extension: F the published extension split.  Start: upper cervical 30 % (as F: assumption), C7-T1 5 %
     (assumption), C2-C7 as [W10]'s start of extension (C5/6 30.21 %, the rest spread: assumption); it ends
     at C3/4 and C4/5 [W10].
   - Lateral bending: F from [L14] (C2/3..C6/7) with the published C7-T1, O-C1 and C1-C2 ranges [WP90].
     Start: O-C1 and C1-C2 at half their F (late recruitment: assumption; no size-resolved data found).
   Per person s0 and s1 are scaled by ``LogNormal(0, share_sigma)`` per level and renormalised ([Z21]: the
   C2-T1 share's coefficient of variation is 7.2 / 18.6 = 0.39, the C0-C2 share's 0.12; sigma 0.2).
4. *Coupling*, linear in the head's primary angle phi (degrees of coupled motion per degree; [Z21] reports
   the coupled motions by their correlation with the primary rotation):
   - Rotation -> bending: upper contralateral 18.2 / 55.5 = 0.33, split O-C1 : C1-C2 = 4.1 : 3.8 [I04a];
     lower ipsilateral 21.4 / 55.5 = 0.39 [Z21], split as the subaxial rotation [I04b] (assumption).  Both
     saturate at the published lateral ranges, which [Z21]'s upper value exceeds at large turns.
   - Rotation -> sagittal: O-C1 extension 0.08 and C1-C2 0.04 per degree (assumption: [I04a] and [S13] report
     13.3 / 12.0 and 6.9 / 4.0 deg at maximal passive rotation, ~0.25 and ~0.1 per degree, supine or lying;
     upright, the head turns horizontally [Z21], and the held-back recording of issue 15 shows only 3.4 deg
     at O-C1 on average at 30 deg of head rotation), balanced by flexion at C5-C6 and C6-C7 [S13] so the head
     stays level (assumption).  A smooth |phi|, ``sqrt(phi^2 + s^2) - s`` with s = 10 deg (assumption), keeps
     it smooth through zero (small turns couple little sagittal motion; a sharper corner is a fold no smooth
     model of H can follow).
   - Bending -> rotation: subaxial to the same side [C06], 10.0 / 21.4 = 0.47 deg per deg of bending ([Z21]'s
     lower region, assumed to hold when bending drives); C1-C2 turns back by 0.8 of the subaxial coupled
     rotation so the face stays forward (assumption; [C06]: the upper direction varies between studies).
   Per person each ratio is scaled by ``LogNormal(0, coupling_sigma)`` ([Z21]: CV 0.24-0.32; sigma 0.3).
5. Each angle saturates smoothly, ``x / (1 + |x/R|^8)^(1/8)``, at the person's range R in its direction, so
   every pose is inside the published limits (``data.joint_limits.within_limits``).

``PriorConfig`` also shifts the process (for tests of a model on a prior other than its training one):
``head_range_scale`` scales T, ``size_dependence`` scales ``s0 - F`` (0 = the same split at every size),
``coupling_scale`` the coupling ratios.

Real sequences: :func:`load_theta_sequences` reads HACK-layout theta arrays (``data/theta_list.npy`` of the
release: ``[T,8,3]`` axis-angle radians per joint in its bone frame, ``models.rig`` convention), a file or a
folder of them.  They carry no frame rate, and need none: their one user, the head-to-neck mapping, is per frame.
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from base.errors import InputError
from base.files import load_npy
from base.rotations import euler_to_axis_angle
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


@dataclass
class PriorConfig:
    """Settings of the generator (the defaults are the prior of the module docstring)."""

    fps: float = 30.0                  # frames per second of the sequences
    seconds: float = 4.0               # length of a sequence
    range_scale_median: float = 0.85   # person's segmental range = published * LogNormal(log median, sigma), clipped
    range_scale_sigma: float = 0.2
    range_scale_min: float = 0.5
    head_range_scale: float = 1.0      # scales the head range per direction (a shift of the prior)
    head_range_sigma: float = 0.19     # per-person log-spread of the head range ([Z21]: 10.8 / 55.5)
    size_dependence: float = 1.0       # scales s0 - F: 0 = the same split at every size, 1 = the sources'
    share_sigma: float = 0.2           # per-person log-jitter of the start and end shares
    coupling_scale: float = 1.0        # scales every coupling ratio (a shift of the prior)
    coupling_sigma: float = 0.3        # per-person log-jitter of the coupling ratios
    kind_weights: list[float] = field(default_factory=lambda: [0.2, 0.2, 0.2, 0.4])  # nod, turn, tilt, combo

    def __post_init__(self) -> None:
        """ValueError naming the first field out of range."""
        for name in ("fps", "seconds", "range_scale_median", "head_range_scale"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if round(self.seconds * self.fps) < 2:
            raise ValueError(f"seconds * fps = {self.seconds * self.fps:g} frames per sequence, expected at least 2")
        for name in ("range_scale_sigma", "head_range_sigma", "share_sigma", "coupling_sigma", "coupling_scale"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"{name} must be non-negative, got {getattr(self, name)}")
        if not 0 < float(self.range_scale_min) <= 1:
            raise ValueError(f"range_scale_min must be in (0, 1] (the published range is the envelope), got "
                             f"{self.range_scale_min}")
        if not 0 <= float(self.size_dependence) <= 1.5:
            raise ValueError(f"size_dependence must be in [0, 1.5] (beyond, some end shares turn negative), got "
                             f"{self.size_dependence}")
        weights = np.asarray(self.kind_weights, dtype=float)
        if weights.shape != (len(MOTION_KINDS),) or not (weights >= 0).all() or not weights.sum() > 0:
            raise ValueError(f"kind_weights must be {len(MOTION_KINDS)} non-negative weights "
                             f"({', '.join(MOTION_KINDS)}) with a positive sum, got {self.kind_weights}")


@dataclass
class Persons:
    """Per-person parameters, batched over N persons.

    ranges_deg:     [N,J,4] segmental flexion, extension, lateral (one side), axial (one side), degrees.
    head_range_deg: [N,4] the head's range per direction (same order), degrees.
    start_shares:   [N,4,J] shares s0 of each direction's first degrees (sum 1 over J).
    end_shares:     [N,4,J] shares s1 of its last degrees (sum 1 over J).
    coupling:       [N,C] ratios in ``COUPLING`` order.
    """

    ranges_deg: np.ndarray
    head_range_deg: np.ndarray
    start_shares: np.ndarray
    end_shares: np.ndarray
    coupling: np.ndarray

    def __len__(self) -> int:
        return len(self.ranges_deg)


@dataclass
class ThetaSequences:
    """N sequences of T frames at ``fps``.

    theta:  [N,T,J,3] float32 axis-angle radians per joint in its anatomical frame.
    euler:  [N,T,J,3] float32 the same poses as Euler angles (ax, ay, az), radians.
    drives: [N,T,3] sagittal, axial, lateral drives in [-1, 1].
    kinds:  [N] motion kind names (``MOTION_KINDS``).
    """

    theta: np.ndarray
    euler: np.ndarray
    drives: np.ndarray
    kinds: list[str]
    persons: Persons
    fps: float


# ----------------------------------------------------------------------------- persons


def _jittered_shares(shares: np.ndarray, rng: np.random.Generator, count: int, sigma: float) -> np.ndarray:
    """[4,J] shares times LogNormal(0, sigma) per person, direction and level, renormalised -> [N,4,J]."""
    out = shares[None] * np.exp(rng.normal(0.0, sigma, (count, *shares.shape)))
    return out / out.sum(-1, keepdims=True)


def sample_persons(count: int, rng: np.random.Generator, config: PriorConfig | None = None) -> Persons:
    """``count`` persons drawn from ``rng`` (see the module docstring, step 1, 3 and 4)."""
    config = PriorConfig() if config is None else config
    scale = np.exp(rng.normal(np.log(config.range_scale_median), config.range_scale_sigma, (count, NUM_JOINTS, 4)))
    ranges = RANGES_DEG[None] * np.clip(scale, config.range_scale_min, 1.0)
    head = (config.head_range_scale * HEAD_RANGE_DEG)[None] * np.clip(
        np.exp(rng.normal(0.0, config.head_range_sigma, (count, 4))), 0.5, 1.5)
    start = FULL_SHARES + config.size_dependence * (START_SHARES - FULL_SHARES)
    end = 2.0 * FULL_SHARES - start
    start = _jittered_shares(start, rng, count, config.share_sigma)
    end = _jittered_shares(end, rng, count, config.share_sigma)
    coupling = config.coupling_scale * np.array(list(COUPLING.values()))[None] * np.exp(
        rng.normal(0.0, config.coupling_sigma, (count, len(COUPLING))))
    return Persons(ranges, head, start, end, coupling)


# ----------------------------------------------------------------------------- segmental model


def cumulative_share(size: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Fraction of a direction's head range each level has moved at drive ``size`` in [0, 1]:
    ``s0 m + (s1 - s0) m^2 / 2`` (the integral of shares going linearly from s0 to s1).

    size [...,1] and start, end [...,J] broadcastable -> [...,J]; sums over J to ``size``.
    """
    return start * size + (end - start) * size**2 / 2


def saturate(x: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Smooth saturation of x towards ``upper`` (> 0) above zero and ``lower`` (< 0) below."""
    bound = np.where(x >= 0, upper, -lower)
    return x / (1.0 + np.abs(x / bound) ** SATURATION_POWER) ** (1.0 / SATURATION_POWER)


def segmental_euler(drives: np.ndarray, persons: Persons) -> np.ndarray:
    """Segmental Euler angles from drives.  drives [N,T,3] in [-1, 1] -> euler [N,T,J,3] radians."""
    ranges = np.radians(persons.ranges_deg)[:, None]            # [N,1,J,4]
    head = np.radians(persons.head_range_deg)[:, None, None]    # [N,1,1,4]
    start, end = persons.start_shares[:, None], persons.end_shares[:, None]  # [N,1,4,J]
    c = {name: value[:, None, None] for name, value in zip(COUPLING, np.moveaxis(persons.coupling, -1, 0))}
    d = drives[..., None]                                       # [N,T,3,1]

    def primary(direction: int, drive: np.ndarray) -> np.ndarray:
        size = np.abs(drive)
        return head[..., direction] * cumulative_share(size, start[:, :, direction], end[:, :, direction])

    sagittal = d[:, :, SAGITTAL_DRIVE]
    ax = np.where(sagittal >= 0, primary(FLEX, sagittal), -primary(EXT, sagittal))
    ay = np.sign(d[:, :, AXIAL_DRIVE]) * primary(AXIAL, d[:, :, AXIAL_DRIVE])
    az = np.sign(d[:, :, LATERAL_DRIVE]) * primary(LAT, d[:, :, LATERAL_DRIVE])

    # Rotation to the left (phi > 0): upper levels bend to the right (+az), lower levels to the left (-az);
    # upper extension balanced by C5-C7 flexion.
    phi = head[..., AXIAL] * d[:, :, AXIAL_DRIVE]               # the head's primary rotation [N,T,1]
    soft = np.radians(SOFT_ABS_DEG)
    phi_magnitude = np.sqrt(phi**2 + soft**2) - soft
    coupled_az = (c["upper_contralateral_bending_per_rotation"] * UPPER_BENDING_LEVELS
                  - c["lower_ipsilateral_bending_per_rotation"] * LOWER_BENDING_LEVELS) * phi
    extension = np.zeros(NUM_JOINTS)
    extension_c1c2, extension_oc1 = extension.copy(), extension.copy()
    extension_c1c2[C1C2], extension_oc1[OC1] = 1.0, 1.0
    upper_extension = (c["oc1_extension_per_rotation"] * extension_oc1
                       + c["c1c2_extension_per_rotation"] * extension_c1c2)
    total_extension = c["oc1_extension_per_rotation"] + c["c1c2_extension_per_rotation"]
    coupled_ax = (total_extension * BALANCING_FLEXION_LEVELS - upper_extension) * phi_magnitude
    # Bending to the right (+az) turns the subaxial levels to the right (-ay); C1-C2 turns back.
    subaxial_rotation = -c["subaxial_rotation_per_bending"] * az * SUBAXIAL_BENDING_LEVELS
    coupled_ay = subaxial_rotation.copy()
    coupled_ay[..., C1C2] -= c["c1c2_counter_rotation_in_bending"][..., 0] * subaxial_rotation.sum(-1)

    lower = np.stack([-ranges[..., EXT], -ranges[..., AXIAL], -ranges[..., LAT]], axis=-1)
    upper = np.stack([ranges[..., FLEX], ranges[..., AXIAL], ranges[..., LAT]], axis=-1)
    euler = np.stack([ax + coupled_ax, ay + coupled_ay, az + coupled_az], axis=-1)
    return saturate(euler, lower, upper)


# ----------------------------------------------------------------------------- drives


def minimum_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk position profile on tau in [0, 1] [FH85]: 10t^3 - 15t^4 + 6t^5."""
    t = np.clip(tau, 0.0, 1.0)
    return t**3 * (10 - 15 * t + 6 * t**2)


def held_transitions(rng: np.random.Generator, time: np.ndarray, amplitude: float) -> np.ndarray:
    """Minimum-jerk moves between targets uniform in [-amplitude, amplitude], each held 0-1 s. -> [T].

    A move over a drive distance D lasts U(0.6, 1.0) + 0.6 D seconds (longer moves take longer, as in
    Fitts' law; assumption), so a full swing from -1 to 1 peaks at about 1.9 drive units per second.
    """
    value = np.full(len(time), rng.uniform(-amplitude, amplitude))
    start = time[0] + rng.uniform(0.0, 0.8)
    current = value[0]
    while start < time[-1]:
        target = rng.uniform(-amplitude, amplitude)
        duration = rng.uniform(0.6, 1.0) + 0.6 * abs(target - current)
        value = value + (target - current) * minimum_jerk((time - start) / duration)
        current = target
        start += duration + rng.uniform(0.0, 1.0)
    return value


def enveloped_oscillation(rng: np.random.Generator, time: np.ndarray, amplitude: float,
                          frequency: tuple[float, float]) -> np.ndarray:
    """A sinusoid at a random frequency, faded in and out with minimum-jerk ramps (0.3 s) over a random window."""
    f = rng.uniform(*frequency)
    span = time[-1] - time[0]
    on = time[0] + rng.uniform(0.0, 0.4) * span
    off = on + rng.uniform(0.4, 1.0) * (time[-1] - on)
    ramp = 0.3
    envelope = minimum_jerk((time - on) / ramp) * (1.0 - minimum_jerk((time - off + ramp) / ramp))
    return amplitude * envelope * np.sin(2 * np.pi * f * (time - on))


def motion_drives(rng: np.random.Generator, num_frames: int, fps: float, kind: str) -> np.ndarray:
    """Drives [T,3] (sagittal, axial, lateral) in [-1, 1] of one motion ``kind`` at ``fps``."""
    if kind not in MOTION_KINDS:
        raise ValueError(f"unknown motion kind '{kind}', expected one of {', '.join(MOTION_KINDS)}")
    time = np.arange(num_frames) / fps
    drives = np.stack([held_transitions(rng, time, 0.12) for _ in range(3)], axis=1)  # small background drift
    main = {"nod": SAGITTAL_DRIVE, "turn": AXIAL_DRIVE, "tilt": LATERAL_DRIVE}
    if kind == "nod":
        drives[:, SAGITTAL_DRIVE] = held_transitions(rng, time, 0.35) + enveloped_oscillation(
            rng, time, rng.uniform(0.05, 0.3), (0.8, 2.0))
    elif kind in main:
        drives[:, main[kind]] = held_transitions(rng, time, 1.0)
        if kind == "turn" and rng.random() < 0.3:  # head shake "no"
            drives[:, AXIAL_DRIVE] += enveloped_oscillation(rng, time, rng.uniform(0.1, 0.25), (1.0, 2.5))
    else:
        drives = np.stack([held_transitions(rng, time, 0.8) for _ in range(3)], axis=1)
        if rng.random() < 0.3:
            axis = rng.integers(3)
            drives[:, axis] += enveloped_oscillation(rng, time, rng.uniform(0.05, 0.25), (0.8, 2.0))
    return saturate(drives, np.float64(-1.0), np.float64(1.0))


# ----------------------------------------------------------------------------- sequences


def sample_sequences(count: int, seed: int, config: PriorConfig | None = None) -> ThetaSequences:
    """``count`` sequences, one new person each, drawn from ``np.random.default_rng(seed)``."""
    config = PriorConfig() if config is None else config
    rng = np.random.default_rng(seed)
    num_frames = int(round(config.seconds * config.fps))
    persons = sample_persons(count, rng, config)
    weights = np.asarray(config.kind_weights, float)
    kinds = [MOTION_KINDS[i] for i in rng.choice(len(MOTION_KINDS), size=count, p=weights / weights.sum())]
    drives = np.stack([motion_drives(rng, num_frames, config.fps, kind) for kind in kinds])
    euler = segmental_euler(drives, persons)
    theta = euler_to_axis_angle(torch.tensor(euler, dtype=torch.float64)).numpy()
    return ThetaSequences(theta.astype(np.float32), euler.astype(np.float32), drives, kinds, persons,
                          float(config.fps))


@torch.no_grad()
def head_rotations(rig, theta: torch.Tensor | np.ndarray, chunk: int = 65536) -> torch.Tensor:
    """Head orientation of poses by the rig's forward kinematics.

    theta [...,J,3] in anatomical joint frames -> [...,3,3] float32."""
    theta = rig.from_anatomical(torch.as_tensor(theta, dtype=torch.float32))
    flat = theta.reshape(-1, theta.shape[-2], 3)
    out = torch.cat([rig.head_rotation(flat[i:i + chunk]) for i in range(0, len(flat), chunk)])
    return out.reshape(*theta.shape[:-2], 3, 3)


# ----------------------------------------------------------------------------- real sequences


@dataclass
class ThetaSequence:
    """A real pose sequence: theta [T,J,3] float32 axis-angle radians (bone frames), read from ``source``."""

    theta: np.ndarray
    source: str


MAX_JOINT_ANGLE = np.pi  # an axis-angle longer than pi is not a rotation vector in the canonical range


def theta_sequence_layout(num_joints: int = NUM_JOINTS) -> str:
    return f"cervical poses [T,{num_joints},3] (axis-angle radians per joint, HACK's data/theta_list.npy layout)"


def load_theta_sequence(path: str | os.PathLike, num_joints: int = NUM_JOINTS) -> ThetaSequence:
    """One ``.npy`` theta sequence ``[T,num_joints,3]``; bad shapes or values raise InputError naming the file."""
    path = Path(path)
    expected = theta_sequence_layout(num_joints)
    theta = load_npy(path, 3, expected)
    if theta.shape[1:] != (num_joints, 3) or len(theta) == 0:
        raise InputError(f"{path}: array of shape {theta.shape}, expected {expected}")
    norms = np.linalg.norm(theta, axis=-1)
    if (norms > MAX_JOINT_ANGLE + 1e-3).any():
        frame, joint = np.argwhere(norms > MAX_JOINT_ANGLE + 1e-3)[0]
        raise InputError(f"{path}: frame {frame}, joint {joint}: rotation of {norms[frame, joint]:.3g} rad, "
                         f"expected axis-angle radians (at most pi); degrees?")
    return ThetaSequence(theta.astype(np.float32), str(path))


def load_theta_sequences(path: str | os.PathLike, num_joints: int = NUM_JOINTS) -> list[ThetaSequence]:
    """A ``.npy`` file or a folder of them (searched recursively, sorted); each must be a theta sequence."""
    path = Path(path)
    if path.is_dir():
        files = sorted(path.rglob("*.npy"))
        if not files:
            raise InputError(f"{path}: folder holds no .npy files; expected {theta_sequence_layout(num_joints)}")
        return [load_theta_sequence(f, num_joints) for f in files]
    if not path.exists():
        raise InputError(f"{path}: not found; expected a .npy file or a folder of "
                         f"{theta_sequence_layout(num_joints)}")
    if path.suffix.lower() != ".npy":
        raise InputError(f"{path}: unsupported format '{path.suffix}', expected .npy "
                         f"{theta_sequence_layout(num_joints)}")
    return [load_theta_sequence(path, num_joints)]
