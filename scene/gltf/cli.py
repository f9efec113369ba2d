"""``python -m scene.gltf``: animated glTF 2.0 (``.glb``) export of a rig driven by a ``params.npz``.

    python -m scene.gltf source=params.npz out=anim.glb [rig=rig.npz] [character=giraffe] [max_influences=8|4]
    python -m scene.gltf source=params.npz out=anim.fbx [fbx_units=cm|m] [...]   (FBX through Blender, scene.fbx)
    python -m scene.gltf source=params.npz out=anim.usdc|anim.usda|anim.usdz [usd_units=cm|m] [...]  (scene.usd)

One binary glTF holds the character at its real size and its whole clip:

- units: glTF's metre (our centimetres / 100), y up, the face towards +z (the project's axes already);
- the mesh: positions and normals of the template, UVs (glTF's v runs down: ``1 - v``), triangles
  (quads fanned, wound counter-clockwise outside).  Vertices are split where the UV layout has seams
  (one glTF vertex per distinct (rig vertex, UV) pair); ``mesh.extras.rig_vertex_index`` [V] maps each
  glTF vertex back to the rig's vertex;
- the cervical skeleton: one node per joint (rest transform relative to the parent as translation +
  rotation), under a common root node, a skin with inverse bind matrices;
- skin weights: up to 8 influences per vertex (``JOINTS_0/WEIGHTS_0`` and ``JOINTS_1/WEIGHTS_1``), the
  largest kept and renormalised in float32; ``max_influences=4`` for engines limited to four, at the
  cost of the error the export report prints;
- morph targets (``mesh.extras.targetNames``): the expressions by name; the larynx slide as K targets
  ``L(eta=1, tau_k)`` at nodes spread over the clip's tau range, weighted ``eta * hat_k(tau)`` (linear
  interpolation in tau, K the fewest meeting ``larynx_error_cm``); the pose correctives, where the rig
  has any, one target per (R - I) feature with the feature as weight; each target also carries the
  change of the normals it makes (``morph_normals``);
- one animation at the clip's frame times: each joint's local rotation (unit quaternions, rest rotation
  times the rotation of theta) and the morph weights.

Identity shape (beta) is not in ``params.npz`` and is left at 0; a fitted person's ``shape_offset``
(``motion.fit``; ``data.params``) is added to the template, so the file holds that person's mesh
(``scene.characters.person_rig``).  Targets that touch few vertices are stored as sparse accessors.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from omegaconf import MISSING

from base.cli import register_config, to_dataclass
from data.params import load_params
from scene.characters import resolve_rig
from scene.fbx import FBX_UNITS, FbxReport, blender_executable, export_fbx
from scene.gltf.document import ExportReport, export_glb
from scene.gltf.mesh import INFLUENCE_CHOICES
from scene.gltf.morphs import DEFAULT_LARYNX_ERROR_CM
from scene.usd import USD_LARYNX_ERROR_CM, USD_SUFFIXES, USD_UNITS, UsdReport, export_usd, require_usd


@dataclass
class GltfConfig:
    """``python -m scene.gltf`` settings (``configs/gltf.yaml``).

    source: params.npz; out: the .glb; rig: a rig file overriding the one recorded in source;
    character: human | giraffe | a character file, built on ``rig`` (``scene.characters``); max_influences: 8 or 4;
    larynx_error_cm: larynx morph-target bound (null: 0.01 cm for GLB and FBX, 0.005 cm for USD, whose
    checks hold it to 0.01 cm); check: evaluate the file's data against the rig; morph_normals: store the
    morph targets' normal changes; fbx_units: cm | m when ``out`` is an .fbx; usd_units: cm | m when ``out``
    is a USD file (.usdc, .usda, .usdz; .usd is usdc).
    """

    source: str = MISSING
    out: str = MISSING
    rig: str | None = None
    character: str | None = None
    max_influences: int = 8
    larynx_error_cm: float | None = None
    check: bool = True
    morph_normals: bool = True
    fbx_units: str = "cm"
    usd_units: str = "cm"
    threads: int = 1

    def __post_init__(self) -> None:
        if self.max_influences not in INFLUENCE_CHOICES:
            raise ValueError(f"max_influences={self.max_influences}: expected one of {list(INFLUENCE_CHOICES)}")
        if self.larynx_error_cm is not None and not self.larynx_error_cm > 0:
            raise ValueError(f"larynx_error_cm={self.larynx_error_cm}: expected a positive bound in cm")
        if self.fbx_units not in FBX_UNITS:
            raise ValueError(f"fbx_units={self.fbx_units}: expected one of {', '.join(FBX_UNITS)}")
        if self.usd_units not in USD_UNITS:
            raise ValueError(f"usd_units={self.usd_units}: expected one of {', '.join(USD_UNITS)}")


register_config("gltf_schema", GltfConfig)


def run(cfg) -> ExportReport | FbxReport | UsdReport:
    """``python -m scene.gltf``: export (the format by ``out``'s suffix) and print the report."""
    settings = to_dataclass(cfg, GltfConfig, where="scene.gltf")
    suffix = Path(settings.out).suffix.lower()
    as_fbx, as_usd = suffix == ".fbx", suffix in USD_SUFFIXES
    if as_fbx:
        blender_executable()  # before any work
    if as_usd:
        require_usd("out=" + settings.out)
    params = load_params(settings.source)
    rig = resolve_rig(params, settings.source, settings.rig, settings.character)
    larynx_error_cm = settings.larynx_error_cm or (USD_LARYNX_ERROR_CM if as_usd else DEFAULT_LARYNX_ERROR_CM)
    if as_usd:
        report = export_usd(params, rig, settings.out, settings.usd_units, max_influences=settings.max_influences,
                            larynx_error_cm=larynx_error_cm, check=settings.check, source=settings.source,
                            morph_normals=settings.morph_normals)
        print(report.summary())
        return report
    if as_fbx:
        report = export_fbx(params, rig, settings.out, settings.fbx_units, take=Path(settings.out).stem,
                            max_influences=settings.max_influences, larynx_error_cm=larynx_error_cm)
        print(report.summary())
        return report
    report = export_glb(params, rig, settings.out, settings.max_influences, larynx_error_cm,
                        settings.check, source=settings.source, morph_normals=settings.morph_normals)
    print(report.summary())
    return report
