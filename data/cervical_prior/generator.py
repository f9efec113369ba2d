"""The generator of the prior: persons, drives -> segmental Euler angles -> theta sequences.

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
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

from base.rotations import euler_to_axis_angle
from data.cervical_prior.drives import motion_drives, saturate
from data.cervical_prior.hack import HACK_COUPLING, HACK_SHARES
from data.cervical_prior.invivo import (
    AXIAL,
    AXIAL_DRIVE,
    BALANCING_FLEXION_LEVELS,
    C1C2,
    COUPLING,
    EXT,
    FLEX,
    FULL_SHARES,
    HEAD_RANGE_DEG,
    LAT,
    LATERAL_DRIVE,
    LOWER_BENDING_LEVELS,
    MOTION_KINDS,
    NUM_JOINTS,
    OC1,
    SAGITTAL_DRIVE,
    SOFT_ABS_DEG,
    START_SHARES,
    SUBAXIAL_BENDING_LEVELS,
    UPPER_BENDING_LEVELS,
)
from data.joint_limits import RANGES_DEG

# The prior's styles (``PriorConfig.style``): (full-range shares F [4,J], start shares s0 [4,J], coupling ratios).
STYLES = {"invivo": (FULL_SHARES, START_SHARES, np.array(list(COUPLING.values()))),
          "hack": (HACK_SHARES, HACK_SHARES, HACK_COUPLING)}

@dataclass
class PriorConfig:
    """Settings of the generator (the defaults are the in-vivo prior of the module docstring; ``style=hack``
    swaps in HACK's shares and no coupling, ``data.cervical_prior.hack``)."""

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
    style: str = "invivo"              # invivo (the in-vivo shares and coupling) | hack (``data.cervical_prior.hack``)

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
        if self.style not in STYLES:
            raise ValueError(f"style={self.style}: expected one of {', '.join(STYLES)}")
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
    full, start, ratios = STYLES[config.style]
    start = full + config.size_dependence * (start - full)
    end = 2.0 * full - start
    start = _jittered_shares(start, rng, count, config.share_sigma)
    end = _jittered_shares(end, rng, count, config.share_sigma)
    coupling = config.coupling_scale * ratios[None] * np.exp(
        rng.normal(0.0, config.coupling_sigma, (count, len(COUPLING))))
    return Persons(ranges, head, start, end, coupling)


# ----------------------------------------------------------------------------- segmental model


def cumulative_share(size: np.ndarray, start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Fraction of a direction's head range each level has moved at drive ``size`` in [0, 1]:
    ``s0 m + (s1 - s0) m^2 / 2`` (the integral of shares going linearly from s0 to s1).

    size [...,1] and start, end [...,J] broadcastable -> [...,J]; sums over J to ``size``.
    """
    return start * size + (end - start) * size**2 / 2


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
