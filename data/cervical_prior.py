"""Anatomical prior of cervical motion: seeded synthetic theta sequences, and the loader of real ones.

HACK drives its 8 cervical joints from one head orientation with a learned
mapping; without motion capture we learn it from this generator, whose
segmental statistics follow the published ranges of motion
(``models.joint_limits.RANGES_DEG``, the single source of the per-level
ranges) plus the facts and assumptions listed below.  Angles are Euler angles
per joint in its anatomical frame (``HeadNeckModel.to_anatomical``; the rig
takes ``rig.from_anatomical(theta)``) (``models.rotations``: ``R = Rz(az) Ry(ay) Rx(ax)``;
``ax`` flexion +, ``ay`` axial rotation + to the subject's left, ``az`` lateral
bending + to the subject's right), joints root to head (``JOINT_LEVELS``).
Head orientation follows by forward kinematics (``HeadNeckModel.head_rotation``).

Generating process
------------------
1. A *person*: each level's four ranges (flexion, extension, lateral bending,
   axial rotation) are the published ones times a factor ``s ~ clip(LogNormal(
   log 0.85, 0.2), 0.5, 1)`` drawn per level and motion.  The published values
   are treated as the envelope (they are the rig's joint limits), so a person
   moves inside them.  Spread: healthy segmental lateral bending C2/3-C6/7
   7.7 +- 2.4, 8.4 +- 2.1, 8.9 +- 3.2, 7.2 +- 2.3, 6.3 +- 2.1 degrees, i.e. a
   coefficient of variation of 0.25-0.36 (Lan et al., BMC Musculoskelet Disord
   15:273, 2014, "The shift of segmental contribution ratio in patients with
   herniated disc during cervical lateral bending"); we take sigma = 0.2 in log
   (assumption, part of that spread is measurement error).  Recruitment and
   coupling parameters vary per person too (below).
2. Three smooth *drives* per sequence in [-1, 1]: sagittal (+ flexion), axial
   (+ to the left) and lateral (+ to the right), the fraction of the person's
   range the head movement asks for: nods (sagittal oscillation 0.8-2 Hz),
   turns, tilts, and combinations, built from minimum-jerk transitions between
   held targets (Flash & Hogan, J Neurosci 5:1688-1703, 1985) and smoothly
   enveloped oscillations, sampled at an explicit ``fps``.
3. *Recruitment*: level j moves ``range_j * u(|d|; k_j) * sign(d)`` for drive
   d, with ``u(m; k) = (1 - exp(-k m)) / (1 - exp(-k))`` (``u = m`` at k = 0):
   k > 0 recruits the level early (concave), k < 0 late (convex); every level
   reaches its full range at |d| = 1, so at full drive the split is the
   published range-of-motion split, and it departs from it in between.
   - Axial rotation: C1-C2 early (k = 2): "increases in angle of axial rotation
     in C1-C2 became smaller with increased head rotation" (Ishii et al.,
     Spine 29(7):E139-E144, 2004, in vivo 3D MRI); subaxial levels late
     (k = -1.5, assumption consistent with it), O-C1 linear.
   - Flexion/extension: O-C1 early (k = 2) and C1-C2 (k = 1): small nods are
     craniocervical ("yes" nodding happens at the atlanto-occipital joint;
     Bogduk & Mercer, Clin Biomech 15:633-648, 2000, review); C5-C6..C7-T1
     late (k = -1).  The k values are our assumption; the literature on the
     order of subaxial sagittal recruitment is not consistent (ibid.).
   - Lateral bending: mostly C2-C7 (their share of the published range is
     already 88%); O-C1 and C1-C2 recruited late (k = -1.5, assumption).
   Per person k += N(0, 0.3).
4. *Coupling* (added to the primary angles, each level's coupled angle in
   proportion to its driver):
   - C2-C3..C7-T1: axial rotation and lateral bending couple to the same side
     (100% agreement of 3D studies below C2: Cook et al., J Manipulative
     Physiol Ther 29:570-575, 2006, systematic review).  Rotation -> same-side
     bending 0.7 deg/deg (C4-C5: 5.5 deg rotation with 4.0 deg same-side
     lateral flexion at maximal rotation, Salem et al., Man Ther 18:339-344,
     2013); bending -> same-side rotation 0.5 deg/deg (assumption).
   - O-C1 and C1-C2 during rotation, per degree of C1-C2 rotation (values at
     maximal rotation, C1-C2 rotating ~37 deg): contralateral lateral bending
     O-C1 0.12 and C1-C2 0.08 (4.1 / 3.8 deg, Ishii 2004; 5.0 / 2.5 deg,
     Salem 2013) and extension O-C1 0.34 and C1-C2 0.15 (13.3 / 6.9 deg,
     Ishii 2004; 12.0 / 4.0 deg, Salem 2013).  The coupled extension uses a
     smooth |.| (softened over 2 deg) so the pose stays smooth through zero.
   - During lateral bending C1-C2 rotates against the subaxial coupled
     rotation by 0.6 of its sum (assumption: the upper cervical spine keeps the
     face forward; its coupling direction varies between studies, Cook 2006).
   Per person each coupling ratio is scaled by LogNormal(0, 0.2).
5. Each angle goes through a smooth saturation ``x / (1 + |x/R|^8)^(1/8)``
   towards the person's range R in its direction, so every pose is inside the
   published limits (``models.joint_limits.within_limits``).

Real sequences: :func:`load_theta_sequences` reads HACK-layout theta arrays
(``data/theta_list.npy`` of the release: ``[T,8,3]`` axis-angle radians per
joint in its bone frame, ``models.rig`` convention), a file or a folder of them.
They carry no frame rate, and need none: their one user, the head-to-neck
mapping, is per frame.
"""
from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from data.errors import InputError

from data.files import load_npy
from models.joint_limits import JOINT_LEVELS, RANGES_DEG
from models.rotations import euler_to_axis_angle

NUM_JOINTS = len(JOINT_LEVELS)
SUBAXIAL = slice(0, 6)          # C7-T1 .. C2-C3
C1C2, OC1 = 6, 7
FLEX, EXT, LAT, AXIAL = range(4)  # columns of RANGES_DEG
SAGITTAL_DRIVE, AXIAL_DRIVE, LATERAL_DRIVE = range(3)
MOTION_KINDS = ("nod", "turn", "tilt", "combo")

# Recruitment earliness k per level (root to head), see the module docstring.
RECRUITMENT_SAGITTAL = np.array([-1.0, -1.0, -1.0, 0.0, 0.0, 0.0, 1.0, 2.0])
RECRUITMENT_AXIAL = np.array([-1.5, -1.5, -1.5, -1.5, -1.5, -1.5, 2.0, 0.0])
RECRUITMENT_LATERAL = np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1.5, -1.5])

# Coupling ratios (degrees of coupled motion per degree of the driver), see the docstring.
COUPLING = {
    "subaxial_rotation_to_bending": 0.7,   # Salem et al. 2013
    "subaxial_bending_to_rotation": 0.5,   # assumption
    "oc1_bending_per_c1c2_rotation": 0.12,  # Ishii 2004, Salem 2013
    "c1c2_bending_per_c1c2_rotation": 0.08,
    "oc1_extension_per_c1c2_rotation": 0.34,
    "c1c2_extension_per_c1c2_rotation": 0.15,
    "c1c2_counter_rotation_in_bending": 0.6,  # assumption
}
SATURATION_POWER = 8
SOFT_ABS_DEG = 2.0


@dataclass(frozen=True)
class PriorConfig:
    """Settings of the generator (mirrored by ``configs/data_task/head2neck_synthetic.yaml``)."""

    fps: float = 30.0                  # frames per second of the sequences
    seconds: float = 4.0               # length of a sequence
    range_scale_median: float = 0.85   # person's range = published * LogNormal(log median, sigma), clipped
    range_scale_sigma: float = 0.2
    range_scale_min: float = 0.5
    recruitment_sigma: float = 0.3     # per-person jitter of the recruitment k
    coupling_sigma: float = 0.2        # per-person log-jitter of the coupling ratios
    kind_weights: tuple[float, float, float, float] = (0.2, 0.2, 0.2, 0.4)  # nod, turn, tilt, combo

    def __post_init__(self) -> None:
        """ValueError naming the first field out of range."""
        for name in ("fps", "seconds", "range_scale_median"):
            if not float(getattr(self, name)) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if round(self.seconds * self.fps) < 2:
            raise ValueError(f"seconds * fps = {self.seconds * self.fps:g} frames per sequence, expected at least 2")
        for name in ("range_scale_sigma", "recruitment_sigma", "coupling_sigma"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"{name} must be a non-negative spread, got {getattr(self, name)}")
        if not 0 < float(self.range_scale_min) <= 1:
            raise ValueError(f"range_scale_min must be in (0, 1] (the published range is the envelope), got "
                             f"{self.range_scale_min}")
        weights = np.asarray(self.kind_weights, dtype=float)
        if weights.shape != (len(MOTION_KINDS),) or not (weights >= 0).all() or not weights.sum() > 0:
            raise ValueError(f"kind_weights must be {len(MOTION_KINDS)} non-negative weights ({', '.join(MOTION_KINDS)}) "
                             f"with a positive sum, got {self.kind_weights}")


@dataclass
class Persons:
    """Per-person parameters, batched over N persons.

    ranges_deg:  [N,J,4] flexion, extension, lateral (one side), axial (one side), degrees.
    recruitment: [N,J,3] k for the sagittal, axial and lateral drives.
    coupling:    [N,C] ratios in ``COUPLING`` order.
    """

    ranges_deg: np.ndarray
    recruitment: np.ndarray
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


def sample_persons(count: int, rng: np.random.Generator, config: PriorConfig = PriorConfig()) -> Persons:
    scale = np.exp(rng.normal(np.log(config.range_scale_median), config.range_scale_sigma, (count, NUM_JOINTS, 4)))
    ranges = RANGES_DEG[None] * np.clip(scale, config.range_scale_min, 1.0)
    base = np.stack([RECRUITMENT_SAGITTAL, RECRUITMENT_AXIAL, RECRUITMENT_LATERAL], axis=1)
    recruitment = base[None] + rng.normal(0.0, config.recruitment_sigma, (count, NUM_JOINTS, 3))
    coupling = np.array(list(COUPLING.values()))[None] * np.exp(
        rng.normal(0.0, config.coupling_sigma, (count, len(COUPLING))))
    return Persons(ranges, recruitment, coupling)


# ----------------------------------------------------------------------------- segmental model


def recruitment_curve(drive: np.ndarray, k: np.ndarray) -> np.ndarray:
    """Odd recruitment ``sign(d) u(|d|; k)``, ``u(m; k) = (1 - e^(-km)) / (1 - e^(-k))`` (u = m at k = 0).

    drive [..., ] and k broadcastable -> same shape.  u(0) = 0, u(1) = 1, C^1 through 0.
    """
    m = np.abs(drive)
    k = np.where(np.abs(k) < 1e-6, 1e-6, k)
    return np.sign(drive) * np.expm1(-k * m) / np.expm1(-k)


def saturate(x: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Smooth saturation of x towards ``upper`` (> 0) above zero and ``lower`` (< 0) below."""
    bound = np.where(x >= 0, upper, -lower)
    return x / (1.0 + np.abs(x / bound) ** SATURATION_POWER) ** (1.0 / SATURATION_POWER)


def segmental_euler(drives: np.ndarray, persons: Persons) -> np.ndarray:
    """Segmental Euler angles from drives.  drives [N,T,3] in [-1, 1] -> euler [N,T,J,3] radians."""
    ranges = np.radians(persons.ranges_deg)[:, None]          # [N,1,J,4]
    k = persons.recruitment[:, None]                            # [N,1,J,3]
    c = dict(zip(COUPLING, np.moveaxis(persons.coupling, -1, 0)))
    c = {name: value[:, None, None] for name, value in c.items()}  # [N,1,1] each
    d = drives[:, :, None, :]                                   # [N,T,1,3]

    sagittal = recruitment_curve(d[..., SAGITTAL_DRIVE], k[..., SAGITTAL_DRIVE])
    ax = np.where(sagittal >= 0, ranges[..., FLEX], ranges[..., EXT]) * sagittal
    ay = ranges[..., AXIAL] * recruitment_curve(d[..., AXIAL_DRIVE], k[..., AXIAL_DRIVE])
    az = ranges[..., LAT] * recruitment_curve(d[..., LATERAL_DRIVE], k[..., LATERAL_DRIVE])

    # Subaxial coupling to the same side: rotation to the left (+ay) with bending to the left (-az).
    sub = np.zeros(NUM_JOINTS, bool)
    sub[SUBAXIAL] = True
    coupled_ay = np.where(sub, -c["subaxial_bending_to_rotation"] * az, 0.0)
    coupled_az = np.where(sub, -c["subaxial_rotation_to_bending"] * ay, 0.0)
    # Upper cervical coupling with C1-C2 rotation: contralateral bending and extension.
    c1c2_rotation = ay[..., C1C2]
    soft = np.radians(SOFT_ABS_DEG)
    rotation_magnitude = np.sqrt(c1c2_rotation**2 + soft**2) - soft
    coupled_az[..., OC1] += c["oc1_bending_per_c1c2_rotation"][..., 0] * c1c2_rotation
    coupled_az[..., C1C2] += c["c1c2_bending_per_c1c2_rotation"][..., 0] * c1c2_rotation
    coupled_ax = np.zeros_like(ax)
    coupled_ax[..., OC1] -= c["oc1_extension_per_c1c2_rotation"][..., 0] * rotation_magnitude
    coupled_ax[..., C1C2] -= c["c1c2_extension_per_c1c2_rotation"][..., 0] * rotation_magnitude
    # C1-C2 turns against the subaxial rotation coupled with lateral bending.
    coupled_ay[..., C1C2] -= c["c1c2_counter_rotation_in_bending"][..., 0] * coupled_ay[..., SUBAXIAL].sum(-1)

    lower = np.stack([-ranges[..., EXT], -ranges[..., AXIAL], -ranges[..., LAT]], axis=-1)
    upper = np.stack([ranges[..., FLEX], ranges[..., AXIAL], ranges[..., LAT]], axis=-1)
    euler = np.stack([ax + coupled_ax, ay + coupled_ay, az + coupled_az], axis=-1)
    return saturate(euler, lower, upper)


# ----------------------------------------------------------------------------- drives


def minimum_jerk(tau: np.ndarray) -> np.ndarray:
    """Minimum-jerk position profile on tau in [0, 1] (Flash & Hogan 1985): 10t^3 - 15t^4 + 6t^5."""
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


def sample_sequences(count: int, seed: int, config: PriorConfig = PriorConfig()) -> ThetaSequences:
    """``count`` sequences, one new person each, drawn from ``np.random.default_rng(seed)``."""
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
