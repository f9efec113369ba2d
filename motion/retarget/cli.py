"""Retarget head-and-neck motion from one character to another: ``python -m motion.retarget``.

    python -m motion.retarget source=params.npz character=giraffe out_dir=giraffe_clip/ [rig=hack_rig.npz]
        [skinning=lbs|dqs] [mesh_format=ply|obj] [export=[glb,html,fbx,usd]] [fbx_units=cm|m]
        [gains=auto|unit|giraffe] [clamp=true]
    python -m motion.retarget mode=picture character=giraffe [rig=hack_rig.npz] out=docs/human_giraffe_poses.png

``source`` is a ``params.npz`` (``data.params``: ``time``, ``fps``, ``theta [T,8,3]`` in the bone frames of
the source rig, ``psi [T,55]``, ``tau [T]``, ``eta [T]``).  ``rig=`` is the source rig (the one whose bone
frames theta is in); without it the rig recorded in the file is used (its checksum must match).
``character`` is the target: ``human`` (the source rig itself), ``giraffe`` (built from the source rig on
the fly, ``scene.characters.build_giraffe``, settings under ``giraffe.*``) or a character file (``.npz``
from ``python -m scene.characters``).

The transfer (:func:`retarget_theta`): each joint's bone-local rotation is taken into its anatomical
frame on the source (``HeadNeckModel.to_anatomical``: +x flexion, +y axial rotation to the left, +z
lateral bend to the right), so a flexion stays a flexion whatever the bone axes are, optionally scaled
per joint and axis (gains on the Euler angles ``R = Rz(az) Ry(ay) Rx(ax)``, ``base.rotations``),
clamped to the target's limits, and brought into the target's bone frames (``from_anatomical``).  With
unit gains and no clamping the anatomical rotations are carried over exactly.  psi goes by expression
name; tau (UV units of the larynx map, which the giraffe keeps) and eta carry over as they are.

A fitted clip (``motion.fit``) keeps its placement (``root_rotation``, ``root_translation``) and
``fit_rms_mm``; its ``shape_offset`` (the person's rest mesh) carries over onto ``character=human`` only,
and the meshes and exports pose that person (``scene.characters.person_rig``).

Outputs in ``out_dir``: ``params.npz`` for the target (theta in the target's bone frames, its head
rotation, ``rig`` = the target's rig file, with its checksum: ``character.npz`` written here when the
character is built on the fly), ``meshes/frame_00000.ply`` ... (``mesh_format=obj`` with UVs), and
``animation.glb`` with ``export=[glb]`` (``scene.gltf.export_glb``; glTF viewers skin linearly, so the GLB
is LBS whatever ``skinning`` is), ``viewer.html`` with ``export=[html]`` (``scene.viewer``: the clip in a browser,
offline), ``animation.fbx`` with ``export=[fbx]`` (``scene.fbx``: needs Blender), ``animation.usdc`` with
``export=[usd]`` (``scene.usd``: UsdSkel; ``usd_format=usda|usdz`` for ``animation.usda``/``.usdz``;
``usd_units=cm|m``).

Giraffe gains (:data:`GIRAFFE_GAINS`): giraffes move the neck mostly at its base; the joint between the
first and second thoracic vertebrae is the fulcrum of giraffe neck motion (Gunji & Endo, "Functional
cervicothoracic boundary modified by anatomical shifts in the neck of giraffes", R. Soc. Open Sci.
3:150604, 2016, doi:10.1098/rsos.150604).  HACK has no T1-T2 joint; c7t1, the lowest, stands in for it.
No per-joint giraffe range of motion in degrees is published in a form we can use, so the values are
ours: c7t1 gets 3x its human flexion/extension and 2x its lateral bend (its sagittal range 9 -> 27
degrees, the largest of the chain, as a fulcrum's should be; lateral 4 -> 8 per side, a mid-cervical
joint's), axial rotation is unchanged (the giraffe's head turns at the atlas as ours does), and every
other joint is scaled down by the common factor that keeps the chain's total for a motion spread over
the joints by their human ranges of motion (``data.joint_limits.RANGES_DEG``; flexion/extension 0.86,
lateral 0.93): the head turns about as far, more of it from the base.  The giraffe's limits are the
human ranges times the gains where a gain exceeds 1 (:func:`giraffe_limits`).
"""
from __future__ import annotations

import os
import time as timer
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from base.cli import register_config, to_dataclass
from base.errors import InputError
from base.files import fresh_output_folder
from data.params import AnimationParams, check_rig, load_params, rig_path, save_params
from models.rig import HeadNeckModel
from motion.retarget.picture import pose_picture
from motion.retarget.posing import MESH_FORMATS, SKINNINGS, supports_skinning, write_meshes
from motion.retarget.transfer import GAIN_CHOICES, default_gains, retarget_params
from scene.characters import GiraffeSettings, load_character
from scene.fbx import FBX_UNITS, blender_executable, export_fbx
from scene.gltf import build_glb, write_glb
from scene.usd import USD_FORMATS, USD_UNITS, export_usd, require_usd
from scene.viewer import build_viewer

MODES = ("retarget", "picture")


@dataclass
class RetargetConfig:
    """``python -m motion.retarget`` settings (``configs/retarget.yaml``).

    mode: retarget (source -> out_dir) or picture (the reference poses of the source rig and the character
    -> out); source: params.npz; out_dir: the output folder (fresh or empty); character: human | giraffe |
    a character .npz; rig: the source rig (default: the one recorded in source; builtin or a rig file);
    skinning: lbs | dqs; meshes: write posed meshes; mesh_format: ply | obj; export: glb (the GLB), html (viewer.html),
    fbx (animation.fbx through Blender; fbx_units cm | m), usd (animation.<usd_format>: usdc | usda | usdz;
    usd_units cm | m);
    gains: auto (the giraffe's on a giraffe) | unit | giraffe; joint_gains: explicit gains, 8 (one per
    joint) or 24 (joint-major, flexion/axial/lateral) numbers, overriding ``gains``; clamp: clamp to the
    target's limits (None: when gains apply); limit_margin: scales the limits; batch: frames posed at once;
    out: the picture (mode=picture); giraffe: the giraffe's shape when built on the fly.
    """

    mode: str = "retarget"
    source: str | None = None
    out_dir: str | None = None
    out: str | None = None
    character: str = "giraffe"
    rig: str | None = None
    skinning: str = "lbs"
    meshes: bool = True
    mesh_format: str = "ply"
    export: list[str] = field(default_factory=list)
    fbx_units: str = "cm"
    usd_format: str = "usdc"
    usd_units: str = "cm"
    gains: str = "auto"
    joint_gains: list[float] | None = None
    clamp: bool | None = None
    limit_margin: float = 1.0
    batch: int = 64
    threads: int = 1
    giraffe: GiraffeSettings = field(default_factory=GiraffeSettings)

    def __post_init__(self) -> None:
        if self.mode not in MODES:
            raise ValueError(f"mode={self.mode}: expected one of {', '.join(MODES)}")
        if self.mode == "retarget" and not (self.source and self.out_dir):
            raise ValueError("mode=retarget needs source=<params.npz> and out_dir=<folder>")
        if self.mode == "picture" and not self.out:
            raise ValueError("mode=picture needs out=<picture.png>")
        for key, value, choices in (("skinning", self.skinning, SKINNINGS), ("gains", self.gains, GAIN_CHOICES),
                                    ("mesh_format", self.mesh_format, MESH_FORMATS)):
            if value not in choices:
                raise ValueError(f"{key}={value}: expected one of {', '.join(choices)}")
        unknown = [e for e in self.export if e not in ("glb", "html", "fbx", "usd")]
        if unknown:
            raise ValueError(f"export={list(self.export)}: expected some of glb, html, fbx, usd")
        for key, value, choices in (("usd_format", self.usd_format, USD_FORMATS),
                                    ("usd_units", self.usd_units, USD_UNITS)):
            if value not in choices:
                raise ValueError(f"{key}={value}: expected one of {', '.join(choices)}")
        if self.fbx_units not in FBX_UNITS:
            raise ValueError(f"fbx_units={self.fbx_units}: expected one of {', '.join(FBX_UNITS)}")
        if self.joint_gains is not None and len(self.joint_gains) not in (8, 24):
            raise ValueError(f"joint_gains has {len(self.joint_gains)} values, expected 8 (per joint) or 24 "
                             "(joint x axis)")
        if not self.limit_margin > 0 or self.batch < 1:
            raise ValueError("limit_margin > 0 and batch >= 1 expected")


register_config("retarget_schema", RetargetConfig)


def resolve_gains(settings: RetargetConfig, target: HeadNeckModel) -> np.ndarray | None:
    if settings.joint_gains is not None:
        values = np.asarray(settings.joint_gains, dtype=np.float64)
        return values.reshape(target.num_joints, 3) if values.size == 3 * target.num_joints else values
    return default_gains(target, settings.gains)


def source_rig(params: AnimationParams, source: str | os.PathLike, rig: str | None) -> tuple[HeadNeckModel, str]:
    """The rig ``params.theta`` is in (``rig`` or the one recorded), checked, and its label."""
    choice = rig if rig else rig_path(params, source)
    if choice is not None and str(choice).startswith("character:"):
        raise InputError(f"{source}: made for '{choice}'; give rig=<its character file>")
    model = HeadNeckModel.from_config(choice)
    check_rig(params, model.rig, source, "rig")
    return model, ("builtin" if choice in (None, "", "builtin") else str(Path(choice).resolve()))


def run(cfg) -> AnimationParams | None:
    """``python -m motion.retarget``: retarget a clip (or render the reference poses) and report."""
    settings = to_dataclass(cfg, RetargetConfig, where="motion.retarget")
    if settings.mode == "picture":
        source = HeadNeckModel.from_config(settings.rig)
        target = HeadNeckModel(load_character(settings.character, source.rig, settings.giraffe))
        pose_picture(settings.out, source, target, resolve_gains(settings, target), skinning=settings.skinning,
                     names=("human", settings.character if settings.character in ("human", "giraffe") else "character"))
        print(f"wrote {settings.out}")
        return None

    if "fbx" in settings.export:
        blender_executable()  # before any work: one line saying how to install it, exit status 2
    if "usd" in settings.export:
        require_usd()         # likewise for usd-core
    started = timer.perf_counter()
    params = load_params(settings.source)
    source, source_label = source_rig(params, settings.source, settings.rig)
    if settings.skinning == "dqs" and not supports_skinning(source, "dqs"):
        raise InputError("skinning=dqs: this version of models.rig has no dual-quaternion skinning yet")
    out_dir = fresh_output_folder(settings.out_dir, ("params.npz", "character.npz", "meshes", "*.glb", "*.usd?"),
                                  "out_dir")
    if settings.character == "human":
        target, label = source, source_label
    else:
        character = load_character(settings.character, source.rig, settings.giraffe)
        if settings.character == "giraffe":
            path = out_dir / "character.npz"
            character.save(path)
            label = str(path.resolve())
        else:
            label = str(Path(settings.character).resolve())
        target = HeadNeckModel(character)
    gains = resolve_gains(settings, target)
    result = retarget_params(params, source, target, label, gains, settings.clamp, settings.limit_margin,
                             source_name=settings.source)
    save_params(out_dir / "params.npz", result)
    lines = [f"retargeted {len(result)} frames at {result.fps:g} fps from {source_label} onto {settings.character} "
             f"(gains: {'none' if gains is None else settings.gains if settings.joint_gains is None else 'given'}, "
             f"clamp: {gains is not None if settings.clamp is None else settings.clamp})",
             f"wrote {out_dir / 'params.npz'}"]
    if settings.meshes:
        posing = timer.perf_counter()
        count = write_meshes(out_dir / "meshes", target, result, settings.skinning, settings.mesh_format,
                             settings.batch)
        lines.append(f"wrote {count} {settings.mesh_format.upper()} meshes ({settings.skinning}) to "
                     f"{out_dir / 'meshes'} in {timer.perf_counter() - posing:.1f} s")
    glb = None
    if {"glb", "html", "fbx"} & set(settings.export):  # one GLB for the file, the page and Blender
        glb = build_glb(result, target, check="glb" in settings.export, source=str(out_dir / "params.npz"),
                        morph_normals=bool({"glb", "html"} & set(settings.export)))
    if "glb" in settings.export:
        lines.append(write_glb(glb, out_dir / "animation.glb").summary())
    if "html" in settings.export:
        companion = None if settings.character == "human" else (params, source)   # the source beside the character
        lines.append(build_viewer(result, target, out_dir / "viewer.html", glb=glb.raw, title=out_dir.name,
                                  companion=companion).summary())
    if "fbx" in settings.export:
        lines.append(export_fbx(result, target, out_dir / "animation.fbx", settings.fbx_units, glb=glb.raw,
                                take=out_dir.name).summary())
    if "usd" in settings.export:
        lines.append(export_usd(result, target, out_dir / f"animation.{settings.usd_format}", settings.usd_units,
                                source=str(out_dir / "params.npz")).summary())
    lines.append(f"done in {timer.perf_counter() - started:.1f} s")
    print("\n".join(lines))
    return result
