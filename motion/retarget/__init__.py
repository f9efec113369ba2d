"""Retarget head-and-neck motion from one character to another: ``python -m motion.retarget``.

    python -m motion.retarget source=params.npz character=giraffe out_dir=giraffe_clip/ [rig=hack_rig.npz]
        [skinning=lbs|dqs] [mesh_format=ply|obj] [export=[glb]] [gains=auto|unit|giraffe] [clamp=true]
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

Outputs in ``out_dir``: ``params.npz`` for the target (theta in the target's bone frames, its head
rotation, ``rig`` = the target's rig file, with its checksum: ``character.npz`` written here when the
character is built on the fly), ``meshes/frame_00000.ply`` ... (``mesh_format=obj`` with UVs), and
``animation.glb`` with ``export=[glb]`` (``scene.gltf.export_glb``; glTF viewers skin linearly, so the GLB
is LBS whatever ``skinning`` is).

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

import inspect
import os
import time as timer
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

from base.cli import register_config, to_dataclass
from base.errors import InputError
from base.files import fresh_output_folder
from base.plots import figure, save_figure
from base.rotations import axis_angle_to_euler, euler_to_axis_angle
from data.joint_limits import RANGES_DEG, euler_limits, range_of_motion_shares
from data.mesh_io import write_obj, write_ply
from data.params import AnimationParams, check_rig, load_params, rig_checksum, rig_path, save_params
from models.rig import HeadNeckModel
from scene.characters import GiraffeSettings, character_kind, load_character
from scene.gltf import export_glb
from scene.preview import framing_camera, shade
from scene.render import outward_faces, render_normals

SKINNINGS = ("lbs", "dqs")
MESH_FORMATS = ("ply", "obj")
GAIN_CHOICES = ("auto", "unit", "giraffe")
MODES = ("retarget", "picture")

# Gains at c7t1 (the giraffe's fulcrum, standing in for T1-T2), per anatomical Euler axis
# (flexion/extension ax, axial rotation ay, lateral bend az): see the module docstring.
FULCRUM_GAINS = np.array([3.0, 1.0, 2.0])


def _giraffe_gains() -> np.ndarray:
    flexion, extension, lateral, axial = RANGES_DEG.T
    ranges = np.stack([flexion + extension, axial, lateral], axis=1)       # [J,3] per Euler axis
    gains = np.ones_like(ranges)
    gains[0] = FULCRUM_GAINS
    # The other joints share what keeps sum_j gain_j * range_j = sum_j range_j per axis.
    rest = (ranges.sum(0) - FULCRUM_GAINS * ranges[0]) / (ranges.sum(0) - ranges[0])
    gains[1:] = rest
    return gains


GIRAFFE_GAINS = _giraffe_gains()   # [8,3]: c7t1 (3, 1, 2), the others (0.860, 1, 0.930)


def giraffe_limits(margin: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """The giraffe's Euler limits [J,3] (radians, (ax, ay, az)): the human's (``euler_limits``) times the
    default gains where they exceed 1 (c7t1: sagittal x3, lateral x2)."""
    lower, upper = euler_limits(margin)
    scale = torch.tensor(np.maximum(GIRAFFE_GAINS, 1.0), dtype=lower.dtype)
    return lower * scale, upper * scale


def character_limits(rig: HeadNeckModel, margin: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Euler limits [J,3] of a character: the giraffe's for a built giraffe, the human's otherwise."""
    return giraffe_limits(margin) if character_kind(rig.rig) == "giraffe" else euler_limits(margin)


def default_gains(target: HeadNeckModel, choice: str = "auto") -> np.ndarray | None:
    """Gains [J,3] for ``choice`` (auto: the giraffe's on a giraffe, none otherwise; unit: none)."""
    if choice not in GAIN_CHOICES:
        raise InputError(f"gains={choice}: expected one of {', '.join(GAIN_CHOICES)}")
    if choice == "giraffe" or (choice == "auto" and character_kind(target.rig) == "giraffe"):
        return GIRAFFE_GAINS.copy()
    return None


def retarget_theta(theta: torch.Tensor, source: HeadNeckModel, target: HeadNeckModel,
                   gains: np.ndarray | torch.Tensor | None = None,
                   limits: tuple[torch.Tensor, torch.Tensor] | None = None) -> torch.Tensor:
    """Carry joint rotations from ``source``'s bone frames to ``target``'s through the anatomical frames.

    Args:
        theta: [T,J,3] axis-angle radians in the source's bone frames.
        source, target: the rigs (same joint names).
        gains: [J,3] or [J] factors on each joint's anatomical Euler angles (flexion, axial, lateral), or None.
        limits: (lower, upper) [J,3] Euler limits (radians) of the target to clamp to, or None.
    Returns:
        [T,J,3] axis-angle in the target's bone frames.  Without gains and limits,
        ``target.to_anatomical(result) == source.to_anatomical(theta)`` exactly.
    """
    if source.joint_names != target.joint_names:
        raise InputError(f"joints differ: source {source.joint_names}, target {target.joint_names}")
    anatomical = source.to_anatomical(theta)
    if gains is not None or limits is not None:
        euler = axis_angle_to_euler(anatomical)
        if gains is not None:
            gains = torch.as_tensor(gains, dtype=euler.dtype)
            euler = euler * (gains[:, None] if gains.ndim == 1 else gains)
        if limits is not None:
            euler = torch.maximum(torch.minimum(euler, limits[1].to(euler)), limits[0].to(euler))
        anatomical = euler_to_axis_angle(euler)
    return target.from_anatomical(anatomical)


def retarget_params(params: AnimationParams, source: HeadNeckModel, target: HeadNeckModel, rig_label: str,
                    gains: np.ndarray | None = None, clamp: bool | None = None, margin: float = 1.0,
                    source_name: str = "params") -> AnimationParams:
    """``params`` (in ``source``'s bone frames) for ``target``: theta retargeted (:func:`retarget_theta`),
    clamped to the target's limits when ``clamp`` (None: when gains are given), psi by expression name,
    tau and eta as they are; ``rig_label`` names the target's rig in the result (with its checksum)."""
    clamp = gains is not None if clamp is None else clamp
    limits = character_limits(target, margin) if clamp else None
    with torch.no_grad():
        # float64 through the Euler angles (the bone <-> anatomical turns are exact signed permutations)
        theta64 = torch.as_tensor(params.theta, dtype=torch.float64)
        theta = retarget_theta(theta64, source, target, gains, limits).float()
        head = target.head_rotation(theta).numpy()
    missing = [n for n in target.expression_names if n not in params.expression_names]
    if missing:
        raise InputError(f"{source_name}: no psi for the character's expressions {missing[:5]}")
    order = [params.expression_names.index(n) for n in target.expression_names]
    producers = dict(params.producers)
    producers.update({"tool": "motion.retarget", "retargeted_from": params.rig})
    return AnimationParams(time=params.time, fps=params.fps, psi=params.psi[:, order], tau=params.tau, eta=params.eta,
                           theta=theta.numpy(), head_rotation=head, joint_names=target.joint_names,
                           expression_names=target.expression_names, rig=rig_label,
                           rig_checksum=rig_checksum(target.rig), producers=producers)


# ----------------------------------------------------------------------------- posing


def supports_skinning(rig: HeadNeckModel, skinning: str) -> bool:
    """Whether ``rig``'s forward pass takes ``skinning=`` (dual quaternions are added to models.rig
    separately); plain LBS always works."""
    return skinning == "lbs" or "skinning" in inspect.signature(rig.forward).parameters


@torch.no_grad()
def pose(rig: HeadNeckModel, params: AnimationParams, skinning: str = "lbs", batch: int = 64,
         frames: np.ndarray | None = None) -> Iterator[tuple[int, torch.Tensor]]:
    """Posed vertices of ``params`` on ``rig`` in batches: yields (first frame, vertices [B,N,3] cm).

    skinning: lbs | dqs (InputError if the rig has no dual-quaternion skinning).
    """
    if skinning not in SKINNINGS:
        raise InputError(f"skinning={skinning}: expected one of {', '.join(SKINNINGS)}")
    if not supports_skinning(rig, skinning):
        raise InputError(f"skinning={skinning}: this version of models.rig has no dual-quaternion skinning yet")
    extra = {"skinning": skinning} if "skinning" in inspect.signature(rig.forward).parameters else {}
    frames = np.arange(len(params)) if frames is None else np.asarray(frames)
    for start in range(0, len(frames), batch):
        index = frames[start:start + batch]
        yield start, rig(torch.as_tensor(params.theta[index]), torch.as_tensor(params.psi[index]),
                         torch.as_tensor(params.tau[index]), torch.as_tensor(params.eta[index]), **extra)


def write_meshes(folder: Path, rig: HeadNeckModel, params: AnimationParams, skinning: str = "lbs",
                 mesh_format: str = "ply", batch: int = 64) -> int:
    """``folder/frame_00000.<mesh_format>`` ... one posed mesh per frame (OBJ with the rig's UVs); returns
    the count."""
    if mesh_format not in MESH_FORMATS:
        raise InputError(f"mesh_format={mesh_format}: expected one of {', '.join(MESH_FORMATS)}")
    faces = rig.rig.faces
    uv = (rig.rig.uv_coords, rig.rig.faces_uv) if len(rig.rig.uv_coords) else (None, None)
    count = 0
    for start, vertices in pose(rig, params, skinning, batch):
        for k, frame in enumerate(vertices.numpy()):
            path = folder / f"frame_{start + k:05d}.{mesh_format}"
            if mesh_format == "ply":
                write_ply(path, frame, faces)
            else:
                write_obj(path, frame, faces, *uv)
            count += 1
    return count


# ----------------------------------------------------------------------------- the reference poses picture

# Head angles of the four reference poses (degrees, anatomical Euler axis), spread over the joints by
# their human ranges of motion in that direction: extension -40 (flexion axis), side-bend 30 (lateral, to
# the right), flexion 40, twist 50 (axial, to the left); each inside every joint's range (the chain's:
# extension 77.4, lateral 61, flexion 60.5, axial 77 degrees).
REFERENCE_POSES = {"extension": (0, -40.0), "side-bend": (2, 30.0), "flexion": (0, 40.0), "twist": (1, 50.0)}
POSE_VIEWS = {"extension": "side", "side-bend": "front", "flexion": "side", "twist": "three_quarter"}


def reference_theta(rig: HeadNeckModel, name: str) -> torch.Tensor:
    """theta [1,J,3] (``rig``'s bone frames) of a reference pose: the head angle of ``REFERENCE_POSES[name]``
    spread over the joints by their human range-of-motion shares in that direction
    (``data.joint_limits.range_of_motion_shares``, anatomical frames)."""
    axis, degrees = REFERENCE_POSES[name]
    positive, negative = range_of_motion_shares()
    share = (positive if degrees > 0 else negative)[:, axis].double()
    euler = torch.zeros(1, rig.num_joints, 3, dtype=torch.float64)
    euler[0, :, axis] = np.radians(degrees) * share
    return rig.from_anatomical(euler_to_axis_angle(euler)).float()


def _still(rig: HeadNeckModel, theta: torch.Tensor, view: str, size: int, skinning: str) -> np.ndarray:
    params = AnimationParams(time=np.zeros(1), fps=1.0, psi=np.zeros((1, len(rig.expression_names))),
                             tau=np.zeros(1), eta=np.ones(1), theta=theta.numpy(),
                             head_rotation=np.eye(3)[None], joint_names=rig.joint_names,
                             expression_names=rig.expression_names)
    camera = framing_camera(rig, params, view, size)
    vertices = next(pose(rig, params, skinning))[1]
    render = render_normals(vertices, outward_faces(rig.template, rig.faces.numpy()), camera)
    return shade(render.normals.numpy(), render.mask.numpy())[0][..., ::-1]   # BGR -> RGB


def pose_picture(path: str | os.PathLike, source: HeadNeckModel, target: HeadNeckModel,
                 gains: np.ndarray | None = None, size: int = 320, skinning: str = "lbs",
                 names: tuple[str, ...] = ("source", "target")) -> None:
    """The source and the target in the four reference poses (rows: characters; columns: poses), rendered
    by ``scene.render`` (shaded as ``scene.preview``), the target's theta retargeted from the source's with
    ``gains`` and clamped to its limits when gains are given; saved atomically to ``path``."""
    fig, axes = figure(nrows=2, ncols=len(REFERENCE_POSES), figsize=(3.2 * len(REFERENCE_POSES), 6.8))
    limits = character_limits(target) if gains is not None else None
    for column, pose_name in enumerate(REFERENCE_POSES):
        theta = reference_theta(source, pose_name)
        with torch.no_grad():
            theta_target = retarget_theta(theta, source, target, gains, limits)
        for row, (rig, value) in enumerate(((source, theta), (target, theta_target))):
            ax = axes[row, column]
            ax.imshow(_still(rig, value, POSE_VIEWS[pose_name], size, skinning))
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"{pose_name} ({POSE_VIEWS[pose_name].replace('_', ' ')} view)")
            if column == 0:
                ax.set_ylabel(names[row])
    save_figure(fig, path)


# ----------------------------------------------------------------------------- command line


@dataclass
class RetargetConfig:
    """``python -m motion.retarget`` settings (``configs/retarget.yaml``).

    mode: retarget (source -> out_dir) or picture (the reference poses of the source rig and the character
    -> out); source: params.npz; out_dir: the output folder (fresh or empty); character: human | giraffe |
    a character .npz; rig: the source rig (default: the one recorded in source; builtin or a rig file);
    skinning: lbs | dqs; meshes: write posed meshes; mesh_format: ply | obj; export: [glb] for the GLB;
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
        unknown = [e for e in self.export if e != "glb"]
        if unknown:
            raise ValueError(f"export={list(self.export)}: only glb is known")
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

    started = timer.perf_counter()
    params = load_params(settings.source)
    source, source_label = source_rig(params, settings.source, settings.rig)
    if settings.skinning == "dqs" and not supports_skinning(source, "dqs"):
        raise InputError("skinning=dqs: this version of models.rig has no dual-quaternion skinning yet")
    out_dir = fresh_output_folder(settings.out_dir, ("params.npz", "character.npz", "meshes", "*.glb"), "out_dir")
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
    if "glb" in settings.export:
        report = export_glb(result, target, out_dir / "animation.glb", source=str(out_dir / "params.npz"))
        lines.append(report.summary())
    lines.append(f"done in {timer.perf_counter() - started:.1f} s")
    print("\n".join(lines))
    return result
