"""The giraffe (:func:`build_giraffe`), from any rig (built-in or the real release).

Every step that moves vertices is a global one-to-one map of space (a monotone stretch along one direction, a monotone
forward stretch of the face, a radial push), so a surface without self-intersections stays without
them (up to the mesh's linear facets; :func:`self_intersections` checks the result):

1. muzzle: the face below the eyes moved forward, the cheeks behind it stretched (``muzzle_factor``),
   fading out above the eyes and below the jaw; optional ossicones (two radial bumps on the crown);
2. neck: a slab of the neck (between T1 and the lowest head vertex, on a slanted level coordinate fitted
   so its level sets separate head from neck) stretched along the rest neck direction, which leans
   forward by ``incline_deg`` from vertical, until the chain T1 -> skull base is ``neck_factor`` times the
   source's; the head and muzzle move with it rigidly (translation only: the face still looks along +z);
3. joints: the vertebrae re-spaced along the stretched chain with giraffe proportions (C2-C7 of one
   length, the atlas ``atlas_share`` of it); each bone keeps its own axes relative to its anatomical
   frame (turned by the minimal rotation from the source's bone direction to the giraffe's), oc1 keeps
   the head's rest rotation, so the anatomical joint frames of the two rigs agree;
4. skinning weights recomputed from each vertex's level along the chain (the source's are wrong on a
   stretched neck: HACK binds the neck at C5-C6 level half to the skull): smooth C1 transitions between
   adjacent bones only, so no vertex is bound to a far joint; head vertices are bound to oc1;
5. expressions (and identity shapes) moved by deformation transfer (:func:`deformation_transfer`,
   Sumner & Popovic 2004), not added raw;
6. the larynx maps kept in UV space (so on the stretched neck they stretch with it, and tau, in UV
   units, slides the larynx the same share of the neck), the larynx direction turned with the neck's
   inclination and its depth scaled by the square root of the local stretch (``larynx_depth_power``).

Giraffe facts used: seven cervical vertebrae, each over 28 cm long (Swaby, "Giraffe", in Mammal Anatomy:
An Illustrated Guide, Marshall Cavendish 2010, p. 71), together 52-54 % of the vertebral column
(Badlangana, Adams & Manger, Zool. J. Linn. Soc. 155:736-757, 2009, doi:10.1111/j.1096-3642.2008.00458.x),
so of similar lengths: C2-C7 equal here, the atlas (a ring without a long body in mammals) shorter (our
choice).  The proportions are ours, not a scan: the chain T1 -> skull base 5 times the human's (~56 cm
on HACK) under a ~30 cm long head (neck ~2 head lengths; an adult giraffe's is ~3).
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import torch

from data.assets import RigData
from data.mesh_io import triangulate
from models.rig import HeadNeckModel
from scene.characters.giraffe_shape import GiraffeSettings, giraffe_geometry, rest_world, smoothstep
from scene.characters.transfer import ZERO_DELTA_CM, deformation_transfer

GIRAFFE_TAG = "giraffe"          # RigData.source of a built giraffe starts with it (character_kind)


def _minimal_rotation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation [3,3] taking unit vector a to unit vector b (Rodrigues)."""
    axis = np.cross(a, b)
    sine, cosine = np.linalg.norm(axis), float(np.dot(a, b))
    if sine < 1e-12:
        return np.eye(3)
    k = axis / sine
    skew = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + sine * skew + (1 - cosine) * skew @ skew



def _local_from_world(world: np.ndarray, parents) -> np.ndarray:
    local = np.empty_like(world)
    for j, parent in enumerate(parents):
        local[j] = world[j] if parent < 0 else np.linalg.inv(world[parent]) @ world[j]
    return local



# ----------------------------------------------------------------------------- skinning along a chain


def chain_weights(level: np.ndarray, joint_levels: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Skinning weights [N,J] from each vertex's level along a chain of J bones.

    Bone j owns the levels between joint j and joint j+1; at each joint j >= 1 (``joint_levels[j]``) the
    weight passes from bone j-1 to bone j over ``widths[j]`` (centred, C1 smoothstep), exactly zero
    beyond; widths narrower than the bones make every vertex bound to at most two adjacent bones.

    Args:
        level: [N] vertex levels; joint_levels: [J] increasing (entry 0 unused); widths: [J] (entry 0 unused).
    Returns:
        [N,J] rows summing to 1.
    """
    j = len(joint_levels)
    above = np.stack([smoothstep((level - joint_levels[k]) / widths[k] + 0.5) for k in range(1, j)], 1)
    ones, zeros = np.ones((len(level), 1)), np.zeros((len(level), 1))
    return np.concatenate([ones, above], 1) - np.concatenate([above, zeros], 1)



def build_giraffe(rig: RigData, settings: GiraffeSettings | None = None) -> RigData:
    """A giraffe with ``rig``'s topology (vertex count, faces, UVs), its own joints, weights and shapes.

    Steps and the facts behind them: the module docstring.  Expression gradients are faded to the
    identity along the neck below the head (over ``expression_fade_cm`` of giraffe neck) and the neck
    below is pinned at rest: Sumner-Popovic transfer each triangle's gradient as is, and HACK's jawOpen
    also shears the throat (up to ~4 cm at C4-C6 level); on the stretched neck that shear would act on
    edges several times longer and open the neck, not the muzzle, and an unpinned faded neck would swing
    with the jaw.  Identity shapes (built-in rig) transfer unfaded.  Pose correctives, where the
    source has any, are dropped (they were fitted to the human's neck).

    Args:
        rig: the source rig (``RigData``, e.g. ``build_procedural_rig()`` or ``RigData.load(path)``).
        settings: the giraffe's shape (defaults: :class:`GiraffeSettings`).
    Returns:
        The giraffe ``RigData`` (``source`` starts with ``giraffe``; its settings in JSON).
    """
    settings = settings or GiraffeSettings()
    geometry = giraffe_geometry(rig, settings)
    world = rest_world(rig)
    parents = [int(p) for p in rig.parents]

    # Bone frames: each chain bone turned by the minimal rotation from its source direction to the
    # giraffe's; the head (oc1) keeps its rest rotation (the neck only translates it).
    new_world = world.copy()
    old_joints = world[:, :3, 3]
    for j in range(len(parents)):
        if j + 1 < len(parents):
            d_old = old_joints[j + 1] - old_joints[j]
            d_new = geometry.joints[j + 1] - geometry.joints[j]
            turn = _minimal_rotation(d_old / np.linalg.norm(d_old), d_new / np.linalg.norm(d_new))
            new_world[j, :3, :3] = turn @ world[j, :3, :3]
        new_world[j, :3, 3] = geometry.joints[j]
    rest_local = _local_from_world(new_world, parents)

    # Skinning along the chain: transitions over weight_blend of the shorter adjacent bone.
    bone = np.diff(geometry.weight_levels)
    widths = settings.weight_blend * np.r_[0.0, np.minimum(bone[:-1], bone[1:]), bone[-1]]  # oc1: the head is unbounded
    skin = chain_weights(geometry.level, geometry.weight_levels, widths)

    # Expression gradients fade out below the head along the giraffe's neck.
    tri = triangulate(rig.faces)
    def fade(level: np.ndarray) -> np.ndarray:
        return smoothstep((level - (geometry.head_start - settings.expression_fade_cm)) / settings.expression_fade_cm)

    n_expr = len(rig.expression_deltas)
    expressions = deformation_transfer(rig.template, rig.expression_deltas, geometry.template, rig.faces,
                                       gradient_weights=fade(geometry.level[tri].mean(1)),
                                       pin_weights=1.0 - fade(geometry.level))
    shapes = rig.shape_deltas
    if shapes.size:
        fixed = np.linalg.norm(rig.expression_deltas, axis=2).max(0) <= ZERO_DELTA_CM
        shapes = deformation_transfer(rig.template, rig.shape_deltas, geometry.template, rig.faces,
                                      fixed=fixed if fixed.any() else None)

    # Larynx: maps kept in UV; direction turned with its bone, depth scaled by stretch ** larynx_depth_power.
    model = HeadNeckModel(rig)
    with torch.no_grad():
        offsets = model.larynx_offsets(torch.zeros(1), torch.ones(1))[0].numpy()
    peak = int(np.argmax(np.linalg.norm(offsets, axis=1)))
    larynx_bone = int(np.clip(np.searchsorted(geometry.joint_levels, geometry.level[peak]) - 1, 0, len(parents) - 1))
    turn = new_world[larynx_bone, :3, :3] @ world[larynx_bone, :3, :3].T
    direction = geometry.stretch[peak] ** settings.larynx_depth_power * (turn @ rig.larynx_direction.astype(np.float64))

    record = {"from": rig.source, "settings": dataclasses.asdict(settings),
              "chain_cm": round(geometry.chain_cm, 3), "source_chain_cm": round(geometry.source_chain_cm, 3),
              "slant": geometry.slant, "larynx_stretch": round(float(geometry.stretch[peak]), 3)}
    return RigData(
        template=geometry.template.astype(np.float32),
        faces=rig.faces.copy(),
        vertex_uv=rig.vertex_uv.copy(),
        joint_names=rig.joint_names.copy(),
        parents=rig.parents.copy(),
        joint_rest_local=rest_local,
        skin_weights=skin.astype(np.float32),
        expression_names=rig.expression_names.copy(),
        expression_deltas=expressions[:n_expr].astype(np.float32),
        larynx_maps=rig.larynx_maps.copy(),
        larynx_direction=direction,
        uv_coords=rig.uv_coords.copy(),
        faces_uv=rig.faces_uv.copy(),
        shape_deltas=np.asarray(shapes, np.float32),
        source=f"{GIRAFFE_TAG} " + json.dumps(record, sort_keys=True),
    )
