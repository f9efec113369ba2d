"""The giraffe's settings and rest shape: its vertices, joint origins and chain levels from a source rig.

How the shape is made and the facts behind it: :mod:`scene.characters.giraffe`.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from base.errors import InputError
from data.assets import JOINT_NAMES, RigData

HEAD_WEIGHT = 0.9                # a source vertex with this much oc1 weight is head


@dataclass
class GiraffeSettings:
    """How :func:`build_giraffe` shapes the giraffe (lengths relative to the source rig).

    neck_factor:    giraffe chain length T1 -> skull base (c7t1 to oc1 origins) over the source's (> 1).
    incline_deg:    forward lean of the rest neck from vertical, degrees.  Our choice, not a measurement:
                    35 (a neck raised ~55 degrees above horizontal, as a standing giraffe is usually seen).
                    Kept at most 40 so each joint's anatomical frame (snapped to the nearest world axes)
                    stays the source's.
    atlas_share:    the atlas (C1, bone c1c2) length over the other vertebrae's (C2-C7 equal).
    muzzle_factor:  the head's front-back depth with the muzzle over the source's (>= 1): the face below
                    the eyes moves forward, the ``muzzle_band_cm`` deep band around the eyes' depth stretches.
    ossicones:      add two ossicones on the crown; ossicone_height: their height over the head's height;
    ossicone_width_deg: their angular radius (Gaussian sigma) seen from the head's centre.
    weight_blend:   skinning transition width at each joint over the shorter adjacent bone (0-1].
    expression_fade_cm: below the head, expression gradients fade to none over this much giraffe neck
                    (see :func:`build_giraffe`).
    larynx_depth_power: the larynx direction's length is multiplied by k ** power, k the neck's local
                    stretch at the larynx (its UV map already makes it k times longer; 0.5: its depth grows
                    as the geometric mean of its new length and unchanged width).
    """

    neck_factor: float = 5.0
    incline_deg: float = 35.0
    atlas_share: float = 0.5
    muzzle_factor: float = 1.5
    muzzle_band_cm: float = 4.0
    ossicones: bool = True
    ossicone_height: float = 0.18
    ossicone_width_deg: float = 9.0
    weight_blend: float = 0.8
    expression_fade_cm: float = 4.0
    larynx_depth_power: float = 0.5

    def __post_init__(self) -> None:
        if not self.neck_factor > 1.0:
            raise ValueError(f"neck_factor={self.neck_factor}: expected > 1 (the giraffe's neck is longer)")
        if not 0.0 <= self.incline_deg <= 40.0:
            raise ValueError(f"incline_deg={self.incline_deg}: expected 0-40 degrees (beyond 45 the neck's "
                             "anatomical frames would snap to other axes)")
        if not 0.1 <= self.atlas_share <= 2.0:
            raise ValueError(f"atlas_share={self.atlas_share}: expected 0.1-2")
        if not self.muzzle_factor >= 1.0:
            raise ValueError(f"muzzle_factor={self.muzzle_factor}: expected >= 1")
        if not 0.0 < self.weight_blend <= 1.0:
            raise ValueError(f"weight_blend={self.weight_blend}: expected in (0, 1]")
        if not self.muzzle_band_cm > 0:
            raise ValueError(f"muzzle_band_cm={self.muzzle_band_cm}: expected > 0")
        if not 0.0 <= self.larynx_depth_power <= 1.0:
            raise ValueError(f"larynx_depth_power={self.larynx_depth_power}: expected 0-1")
        if self.ossicone_height < 0 or self.ossicone_width_deg <= 0 or self.expression_fade_cm <= 0:
            raise ValueError("ossicone_height >= 0, ossicone_width_deg > 0 and expression_fade_cm > 0 expected")



# ----------------------------------------------------------------------------- small helpers


def smoothstep(x: np.ndarray) -> np.ndarray:
    """0 below 0, 1 above 1, 3x^2 - 2x^3 between (C1)."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def smoothstep_integral(x: np.ndarray) -> np.ndarray:
    """Integral of :func:`smoothstep` from -inf to x: 0, x^3 - x^4/2, then x - 1/2."""
    inside = np.clip(x, 0.0, 1.0)
    return np.where(x > 1.0, x - 0.5, inside**3 - 0.5 * inside**4)


def rest_world(rig: RigData) -> np.ndarray:
    """Rest world transforms of the bones [J,4,4] (float64) from the L2P chain."""
    world = []
    for j, parent in enumerate(rig.parents):
        local = rig.joint_rest_local[j].astype(np.float64)
        world.append(local if parent < 0 else world[parent] @ local)
    return np.stack(world)


def _landmark(rig: RigData, names: tuple[str, ...], count: int = 20) -> np.ndarray:
    """Mean rest position [3] of the ``count`` vertices each named expression moves most."""
    points = []
    for name in names:
        if name not in list(rig.expression_names):
            raise InputError(f"rig {rig.source}: no expression '{name}' (needed to find the face's landmarks)")
        k = list(rig.expression_names).index(name)
        magnitude = np.linalg.norm(rig.expression_deltas[k], axis=1)
        points.append(rig.template[np.argsort(magnitude)[-count:]].astype(np.float64))
    return np.concatenate(points).mean(0)


def chain_length(points: np.ndarray) -> float:
    """Length of the polyline through ``points`` [K,3]."""
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum())


# ----------------------------------------------------------------------------- the giraffe


@dataclass
class GiraffeGeometry:
    """What :func:`giraffe_geometry` derives from a source rig (cm, world frame of the source).

    template: [N,3] the giraffe's rest vertices; level: [N] each vertex's position along the chain
    (arc length from T1); joints: [8,3] joint origins; joint_levels: [8] their arc positions;
    weight_levels: [8] where the skinning passes to each bone; head_start: arc position where the rigid head
    begins; muzzle_shift: [N] forward shift of each vertex by the muzzle (cm); neck_axis: [3] the rest neck
    direction; stretch: [N] local stretch along the neck (1 outside it); slant: the fitted level slant.
    """

    template: np.ndarray
    level: np.ndarray
    joints: np.ndarray
    joint_levels: np.ndarray
    weight_levels: np.ndarray
    head_start: float
    muzzle_shift: np.ndarray
    neck_axis: np.ndarray
    stretch: np.ndarray
    slant: float
    source_chain_cm: float
    chain_cm: float


def _head_maps(rig: RigData, settings: GiraffeSettings, vertices: np.ndarray, head_level: float,
               slant: float, origin: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The muzzle and the ossicones: one-to-one maps of space applied to ``vertices`` [K,3]; returns the
    moved vertices and the muzzle's forward shift [K]."""
    eye = _landmark(rig, ("eyeBlink_L", "eyeBlink_R"))
    chin = _landmark(rig, ("jawOpen",))
    face_height = eye[1] - chin[1]
    x, y, z = vertices.T
    # Muzzle: z' = z + L g(y, z) S((z - z0) / w): the face in front of z0 + w moves forward by L g, the band
    # behind it stretches.  S and g are C1 smoothsteps with dS/dz >= 0 and dg/dz >= 0, so z' is strictly
    # increasing in z for every (x, y): one-to-one.  g fades out above the eyes (on y) and below the jaw
    # (on the slanted neck level, which grows with z).
    depth = vertices[:, 2].max() - vertices[:, 2].min()
    length = (settings.muzzle_factor - 1.0) * depth
    band = settings.muzzle_band_cm
    z0 = eye[2] - 0.5 * band   # centred on the eyes' depth (their height keeps them in place: g ~ 0 there)
    full = eye[1] - 0.4 * face_height
    upper = 1.0 - smoothstep((y - full) / (eye[1] + 0.5 - full))
    level = (y - origin[1]) + slant * (z - origin[2])
    lower = smoothstep((level - head_level) / (0.3 * face_height))
    shift = length * upper * lower * smoothstep((z - z0) / band)
    moved = vertices + np.outer(shift, [0.0, 0.0, 1.0])
    if settings.ossicones and settings.ossicone_height > 0:
        # Radial push r -> r + b(direction) from the head's centre: one-to-one along every ray.
        top = vertices[:, 1].max()
        centre = np.array([0.0, 0.5 * (eye[1] + top), eye[2] - 0.5 * (eye[2] - vertices[:, 2].min())])
        height = settings.ossicone_height * (top - chin[1])
        sigma = np.radians(settings.ossicone_width_deg)
        rel = moved - centre
        radius = np.linalg.norm(rel, axis=1)
        direction = rel / np.maximum(radius, 1e-9)[:, None]
        push = np.zeros(len(moved))
        for side in (1.0, -1.0):
            axis = np.array([0.32 * side, 1.0, -0.25])
            axis /= np.linalg.norm(axis)
            angle = np.arccos(np.clip(direction @ axis, -1.0, 1.0))
            push += height * np.exp(-0.5 * (angle / sigma) ** 2)
        moved = moved + push[:, None] * direction
    return moved, shift


def giraffe_geometry(rig: RigData, settings: GiraffeSettings) -> GiraffeGeometry:
    """The giraffe's rest vertices, joints and chain levels from ``rig`` (see :func:`build_giraffe`)."""
    world = rest_world(rig)
    joints = world[:, :3, 3]
    origin = joints[0]
    template = rig.template.astype(np.float64)
    weights = rig.skin_weights.astype(np.float64)
    head = weights[:, -1] >= HEAD_WEIGHT
    if not head.any() or head.all():
        raise InputError(f"rig {rig.source}: no vertex split into head (oc1 weight >= {HEAD_WEIGHT}) and neck")
    rel = template - origin

    # The slanted level h = dy + s dz whose lowest head vertex is highest: its level sets part head and neck.
    slants = np.linspace(0.0, 1.2, 121)
    lowest = np.array([(rel[head, 1] + s * rel[head, 2]).min() for s in slants])
    slant = float(slants[np.argmax(lowest)])
    head_level = float(lowest.max())
    normal = np.array([0.0, 1.0, slant])
    if head_level <= 1.0:
        raise InputError(f"rig {rig.source}: the head reaches down to T1 (c7t1); no neck to stretch")

    moved, muzzle_shift = _head_maps(rig, settings, template, head_level, slant, origin)

    # Neck slab [lo, hi] on h, smoothstep-edged stretch density, exactly zero outside: D(h) = extra * R(h).
    ramp = 0.15 * head_level
    lo, hi = ramp, head_level - ramp

    def fraction(h: np.ndarray) -> np.ndarray:
        total = hi - lo - ramp
        return ramp * (smoothstep_integral((h - lo) / ramp) - smoothstep_integral((h - hi + ramp) / ramp)) / total

    incline = np.radians(settings.incline_deg)
    axis = np.array([0.0, np.cos(incline), np.sin(incline)])

    # The source chain densely sampled, its levels, and the length the giraffe's must have.
    samples = np.concatenate([np.linspace(joints[k], joints[k + 1], 64, endpoint=False) for k in range(len(joints) - 1)]
                             + [joints[-1:]])
    sample_h = (samples - origin) @ normal
    if (np.diff(sample_h) <= 0).any():
        raise InputError(f"rig {rig.source}: the cervical chain does not rise monotonically along the neck level")
    source_length = chain_length(joints)
    target_length = settings.neck_factor * source_length

    # Vertebrae re-spaced along the stretched chain: C7..C2 of one length, the atlas atlas_share of it.
    lengths = np.r_[np.ones(len(JOINT_NAMES) - 2), settings.atlas_share]

    step = target_length * lengths / lengths.sum()          # the bones' lengths (chords)

    def stretched(extra: float):
        """The mapped chain samples, their arc positions, the joints walked along them from T1 at chord
        distances ``step`` (the last one at the chain's end, the skull base), the joints' arc positions,
        and the atlas chord's excess over its length (None where the chain is too short for the walk)."""
        chain = samples + extra * fraction(sample_h)[:, None] * axis
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(chain, axis=0), axis=1))]
        walked, levels, k = [chain[0]], [0.0], 1
        for length in step[:-1]:
            distance = np.linalg.norm(chain[k:] - walked[-1], axis=1)
            ahead = np.flatnonzero(distance >= length)     # first sample at least `length` from the last joint
            if not len(ahead):
                return chain, arc, None, None, None
            k += int(ahead[0])
            a, d = chain[k - 1], chain[k] - chain[k - 1]
            f = a - walked[-1]
            qa, qb, qc = d @ d, 2 * d @ f, f @ f - length**2
            t = (-qb + np.sqrt(max(qb * qb - 4 * qa * qc, 0.0))) / (2 * qa)   # the exact point on that segment
            walked.append(a + t * d)
            levels.append(arc[k - 1] + t * np.sqrt(qa))
        walked.append(chain[-1])
        levels.append(arc[-1])
        excess = float(np.linalg.norm(chain[-1] - walked[-2]) - step[-1])
        return chain, arc, np.stack(walked), np.array(levels), excess

    low, high = 0.0, 10.0 * target_length
    for _ in range(60):  # the longer the stretch, the longer the atlas chord left at the end
        mid = 0.5 * (low + high)
        excess = stretched(mid)[4]
        low, high = (mid, high) if excess is None or excess < 0 else (low, mid)
    extra = 0.5 * (low + high)
    chain, arc, new_joints, joint_levels, _ = stretched(extra)
    if new_joints is None:
        raise InputError(f"rig {rig.source}: could not re-space the vertebrae along the stretched neck")

    h_moved = (moved - origin) @ normal
    giraffe = moved + extra * fraction(h_moved)[:, None] * axis

    # A vertex's level along the chain: the arc position of the chain sample on its h level (slope 1 beyond).
    def level_of(h: np.ndarray) -> np.ndarray:
        inside = np.interp(h, sample_h, arc)
        return inside + np.minimum(h - sample_h[0], 0.0) + np.maximum(h - sample_h[-1], 0.0)

    level = level_of(h_moved)
    density = np.clip((smoothstep((h_moved - lo) / ramp) - smoothstep((h_moved - hi + ramp) / ramp)), 0, 1)
    stretch = 1.0 + extra * density / (hi - lo - ramp) * float(axis @ normal)

    head_start = float(level_of(np.array([hi]))[0])
    weight_levels = joint_levels.copy()
    # The head (rigid above the slab) is oc1's; the atlas keeps at least half its length of skin.
    weight_levels[-1] = max(min(joint_levels[-1], head_start), joint_levels[-2] + 0.5 * step[-1])
    return GiraffeGeometry(template=giraffe, level=level, joints=new_joints, joint_levels=joint_levels,
                           weight_levels=weight_levels, head_start=head_start, muzzle_shift=muzzle_shift,
                           neck_axis=axis, stretch=stretch, slant=slant, source_chain_cm=source_length,
                           chain_cm=chain_length(new_joints))
