"""Characters: same-topology rigs (HACK's template, its own joints), and a procedural giraffe built from any rig.

    python -m scene.characters kind=giraffe [rig=hack_rig.npz] out=giraffe.npz
    python -m scene.characters kind=obj obj=my_giraffe.obj joints=my_bones.json [rig=hack_rig.npz] out=mine.npz

A character is a :class:`data.assets.RigData` (``models.rig.HeadNeckModel`` poses it) with the template's
vertex count, faces and UVs, and its own 8 cervical joint rest frames, skinning weights, expression deltas
and larynx data: theta, psi, tau and eta carry over joint for joint (every mammal has seven cervical
vertebrae; HACK's eight joints c7t1 ... oc1 are the joints between them, T1 and the skull).

- :func:`load_character` (:mod:`scene.characters.loading`): a rig file, ``human`` (the source rig itself),
  ``giraffe`` (built here), or an OBJ with the template's topology plus a joints JSON in the release's
  ``bones_neutral.json`` layout (:func:`character_from_obj`; an artist's own character, as the paper's
  giraffe); :func:`resolve_rig`: the rig (or character) a params file drives; :func:`person_rig`: that rig
  with the params' fitted ``shape_offset`` (``motion.fit``) on its template, what every exporter poses.
- :func:`build_giraffe`: the giraffe, from any rig (built-in or the real release); how and why:
  :mod:`scene.characters.giraffe` (its rest shape: :mod:`scene.characters.giraffe_shape`).
- :func:`deformation_transfer` (:mod:`scene.characters.transfer`) moves the expression and identity shapes
  onto a new mesh; :func:`self_intersections` (:mod:`scene.characters.intersections`) checks a mesh.
- The command line: :mod:`scene.characters.cli`.
"""
from scene.characters.cli import CharactersConfig, run
from scene.characters.giraffe import GIRAFFE_TAG, build_giraffe, chain_weights
from scene.characters.giraffe_shape import (
    HEAD_WEIGHT,
    GiraffeGeometry,
    GiraffeSettings,
    chain_length,
    giraffe_geometry,
    rest_world,
)
from scene.characters.intersections import new_self_intersections, self_intersections
from scene.characters.loading import (
    CHARACTER_NAMES,
    character_from_obj,
    character_kind,
    load_character,
    person_rig,
    read_joints_json,
    resolve_rig,
)
from scene.characters.transfer import ZERO_DELTA_CM, deformation_transfer

__all__ = [
    "CHARACTER_NAMES", "GIRAFFE_TAG", "HEAD_WEIGHT", "ZERO_DELTA_CM", "CharactersConfig", "GiraffeGeometry",
    "GiraffeSettings", "build_giraffe", "chain_length", "chain_weights", "character_from_obj", "character_kind",
    "deformation_transfer", "giraffe_geometry", "load_character", "new_self_intersections", "person_rig",
    "read_joints_json",
    "resolve_rig", "rest_world", "run", "self_intersections",
]
