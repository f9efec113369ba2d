"""``python -m scene.characters``: build a giraffe from a rig, or a character from an OBJ and its joints.

    python -m scene.characters kind=giraffe [rig=hack_rig.npz] out=giraffe.npz [giraffe.neck_factor=5 ...]
    python -m scene.characters kind=obj obj=my_giraffe.obj joints=my_bones.json [rig=hack_rig.npz] out=mine.npz

The giraffe's shape is ``giraffe.*`` (:class:`scene.characters.giraffe_shape.GiraffeSettings`; how it is
built: :mod:`scene.characters.giraffe`); an OBJ character: :func:`scene.characters.loading.character_from_obj`.
``check=true`` counts the rest mesh's self-intersections and refuses a giraffe with more than its source.
"""
from __future__ import annotations

import json
import time
from dataclasses import dataclass, field

from omegaconf import MISSING

from base.cli import register_config, to_dataclass
from base.errors import InputError
from data.assets import RigData
from models.rig import HeadNeckModel
from scene.characters.giraffe import GIRAFFE_TAG, build_giraffe
from scene.characters.giraffe_shape import GiraffeSettings
from scene.characters.intersections import new_self_intersections, self_intersections
from scene.characters.loading import character_from_obj


@dataclass
class CharactersConfig:
    """``python -m scene.characters`` settings (``configs/characters.yaml``).

    kind: giraffe (built from ``rig``) or obj (``obj`` + ``joints`` on ``rig``'s topology); rig: the source
    rig file (None / builtin: the built-in rig); out: the character file (.npz); check: count the rest
    mesh's self-intersections (and refuse a giraffe that has more than its source); giraffe: the shape.
    """

    kind: str = "giraffe"
    out: str = MISSING
    rig: str | None = None
    obj: str | None = None
    joints: str | None = None
    check: bool = True
    threads: int = 1
    giraffe: GiraffeSettings = field(default_factory=GiraffeSettings)

    def __post_init__(self) -> None:
        if self.kind not in ("giraffe", "obj"):
            raise ValueError(f"kind={self.kind}: expected giraffe or obj")
        if self.kind == "obj" and not (self.obj and self.joints):
            raise ValueError("kind=obj needs obj=<mesh.obj> and joints=<bones.json>")


register_config("characters_schema", CharactersConfig)


def run(cfg) -> RigData:
    """``python -m scene.characters``: build or load the character, check it, save it."""
    settings = to_dataclass(cfg, CharactersConfig, where="scene.characters")
    started = time.perf_counter()
    base = HeadNeckModel.from_config(settings.rig).rig
    if settings.kind == "giraffe":
        character = build_giraffe(base, settings.giraffe)
    else:
        character = character_from_obj(settings.obj, settings.joints, base)
    built = time.perf_counter() - started
    lines = [f"{settings.kind}: {len(character.template)} vertices, {len(character.faces)} faces "
             f"(from {base.source}) in {built:.1f} s"]
    if settings.kind == "giraffe":
        record = json.loads(character.source[len(GIRAFFE_TAG):])
        ratio = record["chain_cm"] / record["source_chain_cm"]
        lines.append(f"neck chain T1 -> skull base {record['chain_cm']:.1f} cm "
                     f"(source {record['source_chain_cm']:.1f} cm, x{ratio:.2f})")
    if settings.check:
        base_hits = len(self_intersections(base.template, base.faces))
        new = new_self_intersections(base.template, character.template, base.faces)
        lines.append(f"self-intersecting triangle pairs at rest: {len(new)} new "
                     f"(the source has {base_hits} of its own)")
        if settings.kind == "giraffe" and len(new):
            raise InputError(f"the giraffe built from {base.source} intersects itself at rest ({len(new)} triangle "
                             "pairs beyond the source's); try a smaller muzzle_factor, ossicone_height or incline_deg")
    character.save(settings.out)
    lines.append(f"wrote {settings.out}")
    print("\n".join(lines))
    return character
