"""Loading characters: a rig file, ``human``, ``giraffe`` (built), or an OBJ with the template's topology
plus a joints JSON; the rig (or character) a params file drives (:func:`resolve_rig`), and the person's rig
when the params carry a fitted shape (:func:`person_rig`)."""
from __future__ import annotations

import dataclasses
import json
import os
from pathlib import Path

import numpy as np

from base.errors import InputError, require_file
from data.assets import RigData, rest_transforms_from_bones, with_shape_offset
from data.mesh_io import read_obj, triangulate
from data.params import AnimationParams, check_rig, rig_path
from models.rig import HeadNeckModel
from scene.characters.giraffe import GIRAFFE_TAG, build_giraffe
from scene.characters.giraffe_shape import GiraffeSettings
from scene.characters.transfer import deformation_transfer

CHARACTER_NAMES = ("human", "giraffe")


def character_kind(rig: RigData) -> str:
    """``giraffe`` for a rig built by :func:`build_giraffe` (also after saving and loading), else ``human``."""
    return GIRAFFE_TAG if str(rig.source).startswith(GIRAFFE_TAG) else "human"


def _same_topology(base: RigData, vertices: np.ndarray, faces: np.ndarray | None, path: Path) -> None:
    n = len(base.template)
    if len(vertices) != n:
        raise InputError(f"{path}: {len(vertices)} vertices, expected the template's {n} (same topology as the "
                         f"rig {base.source})")
    if faces is not None and len(faces):
        base_tri, tri = triangulate(base.faces), triangulate(faces)
        if base_tri.shape != tri.shape or not np.array_equal(base_tri, tri):
            differ = next((i for i in range(min(len(base_tri), len(tri))) if not np.array_equal(base_tri[i], tri[i])),
                          min(len(base_tri), len(tri)))
            raise InputError(f"{path}: faces differ from the template's (first at triangle {differ + 1} of the "
                             f"fan-split faces; {len(tri)} vs {len(base_tri)} triangles); expected the template's "
                             f"topology")


def read_joints_json(path: str | os.PathLike) -> tuple[list[str], np.ndarray, np.ndarray]:
    """Joint names, parents and rest transforms [J,4,4] from a joints JSON in the release's
    ``bones_neutral.json`` layout (``{name: {matrix, head, length, parent}}``, root to head)."""
    path = require_file(path, "joints")
    try:
        bones = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as e:
        raise InputError(f"{path}: malformed JSON ({e}); expected bones in the bones_neutral.json layout") from None
    if not isinstance(bones, dict) or not all(isinstance(b, dict) for b in bones.values()):
        raise InputError(f"{path}: expected an object of bones {{name: {{matrix, head, length, parent}}}} "
                         f"(the release's bones_neutral.json layout)")
    for name, bone in bones.items():
        for key, shape in (("matrix", (3, 3)), ("head", (3,))):
            try:
                value = np.asarray(bone.get(key), dtype=np.float64)
            except (TypeError, ValueError):
                raise InputError(f"{path}: bone '{name}' '{key}' is not numbers, expected {list(shape)}") from None
            if key in bone and value.shape != shape:
                raise InputError(f"{path}: bone '{name}' '{key}' has shape {list(value.shape)}, expected {list(shape)}")
        if "length" in bone and not isinstance(bone["length"], (int, float)):
            raise InputError(f"{path}: bone '{name}' 'length' is not a number")
    return rest_transforms_from_bones(bones, path)


def character_from_obj(obj_path: str | os.PathLike, joints_path: str | os.PathLike, base: RigData) -> RigData:
    """A character from an OBJ with ``base``'s topology and a joints JSON (``bones_neutral.json`` layout).

    The OBJ gives the rest vertices (cm, y up, face +z; same vertex order and faces as ``base``), the JSON
    the joint rest frames.  The skinning weights are ``base``'s (the same vertex is the same point of the
    body), the expression and identity shapes are moved onto the new mesh by :func:`deformation_transfer`,
    the larynx maps and direction are ``base``'s.  Errors name the file.
    """
    obj_path = require_file(obj_path, "obj")
    mesh = read_obj(obj_path)
    _same_topology(base, mesh.vertices, mesh.faces, obj_path)
    names, parents, rest_local = read_joints_json(joints_path)
    if not np.array_equal(parents, base.parents):
        raise InputError(f"{joints_path}: parents {parents.tolist()}, expected {base.parents.tolist()}")
    expressions = deformation_transfer(base.template, base.expression_deltas, mesh.vertices, base.faces)
    shapes = base.shape_deltas
    if shapes.size:
        shapes = deformation_transfer(base.template, shapes, mesh.vertices, base.faces)
    return dataclasses.replace(
        base, template=mesh.vertices.astype(np.float32), joint_names=np.array(names), joint_rest_local=rest_local,
        expression_deltas=expressions.astype(np.float32), shape_deltas=np.asarray(shapes, np.float32),
        pose_correctives=np.zeros((0, 0), np.float32),
        source=f"character {Path(obj_path).resolve()} + {Path(joints_path).resolve()} on {base.source}")


def load_character(spec: str, source: RigData, settings: GiraffeSettings | None = None) -> RigData:
    """The character ``spec`` names: ``human`` (``source`` itself), ``giraffe`` (built from ``source``), or a
    rig / character file (``.npz``).  OBJ characters: :func:`character_from_obj`."""
    if spec == "human":
        return source
    if spec == GIRAFFE_TAG:
        return build_giraffe(source, settings)
    path = Path(spec)
    if path.suffix.lower() == ".obj":
        raise InputError(f"{spec}: an OBJ character needs its joints; make it first with "
                         f"python -m scene.characters kind=obj obj={spec} joints=bones.json out=character.npz")
    if path.suffix.lower() != ".npz" and not path.exists():
        raise InputError(f"character={spec}: expected {' | '.join(CHARACTER_NAMES)} or a character file (.npz)")
    return RigData.load(path)


def resolve_rig(params: AnimationParams, source: str | os.PathLike, rig: str | None = None,
                character: str | None = None) -> HeadNeckModel:
    """The rig ``params`` drive, checked against them (joints, expressions, checksum).

    ``character`` (``human``, ``giraffe`` or a character file; ``scene.characters.load_character``) built
    on ``rig`` (a rig file; default the built-in rig); else ``rig``; else the rig recorded in ``params``
    (a file, the built-in rig, or ``character:<name>`` built on the built-in rig).
    """
    key = "character" if character else "rig"
    if not character:
        choice = rig if rig else rig_path(params, source)
        if choice is not None and str(choice).startswith("character:"):
            character, key = str(choice).split(":", 1)[1], "rig"
        else:
            model = HeadNeckModel.from_config(choice)
            check_rig(params, model.rig, source, key)
            return model
    model = HeadNeckModel(load_character(character, HeadNeckModel.from_config(rig).rig))
    check_rig(params, model.rig, source, key)
    return model


def person_rig(model: HeadNeckModel, params: AnimationParams, source: str | os.PathLike = "params") -> HeadNeckModel:
    """The rig that poses ``params`` as the person they were fitted to: ``model`` (the BASE rig, the one
    ``params.rig_checksum`` names) with ``params.shape_offset`` added to its template
    (``data.assets.with_shape_offset``), or ``model`` itself when the params carry no shape.  Every
    exporter calls it with the base rig, so a fitted person exports as that person."""
    if params.shape_offset is None:
        return model
    return HeadNeckModel(with_shape_offset(model.rig, params.shape_offset, str(source)), skinning=model.skinning)
