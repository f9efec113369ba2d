"""``anim.usdc`` / ``.usda`` / ``.usdz``: the clip as one UsdSkel stage (:mod:`scene.usd.stage`), written
atomically; usdz packaged with ``UsdUtils.CreateNewUsdzPackage`` (Apple's Quick Look, Reality Composer).

The arrays are the GLB's (:func:`scene.gltf.export_data`: skin, targets, rotations, weights), so both
files show the same clip; only the units differ (the GLB's metre, here ``usd_units``: cm by default,
``metersPerUnit`` 0.01, or m).
"""
from __future__ import annotations

import json
import os
import tempfile
import time as timer
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.errors import InputError
from base.files import atomic_path
from data.params import AnimationParams
from models.rig import HeadNeckModel
from scene.gltf import METRES_PER_CM, export_data, export_error_cm
from scene.usd.stage import build_stage
from scene.usd.weights import within_unit_weights

USD_FORMATS = ("usdc", "usda", "usdz")
USD_UNITS = ("cm", "m")
USD_SUFFIXES = (".usdc", ".usda", ".usdz", ".usd")      # .usd: USD's own default, the binary crate format
METRES_PER_UNIT = {"cm": METRES_PER_CM, "m": 1.0}
# The larynx targets' interpolation bound for USD: half the GLB's 0.01 cm, so that the file as USD skins it
# (checked with UsdSkel.BakeSkinning within 0.01 cm) keeps a margin for the float32 skin (measured:
# benchmarks/README.md, "USD export").
USD_LARYNX_ERROR_CM = 0.005
INSTALL_HINT = "pip install usd-core (Pixar's USD for Python, a dependency of this project)"


class UsdMissing(InputError):
    """usd-core (the ``pxr`` modules) is not installed."""


def require_usd(purpose: str = "export=[usd]") -> None:
    """UsdMissing, saying how to install it, unless ``pxr`` (usd-core) imports."""
    try:
        import pxr.UsdSkel  # noqa: F401
        import pxr.UsdUtils  # noqa: F401
    except ImportError as error:
        raise UsdMissing(f"{purpose} needs usd-core, which is not installed ({error}): {INSTALL_HINT}") from None


def usd_format(path: str | os.PathLike) -> str:
    """usdc | usda | usdz from ``path``'s suffix (``.usd``: usdc); InputError for any other suffix."""
    suffix = Path(path).suffix.lower()
    if suffix not in USD_SUFFIXES:
        raise InputError(f"{path}: a USD file ends in {', '.join(USD_SUFFIXES)}")
    return "usdc" if suffix == ".usd" else suffix[1:]


def require_writable(path: str | os.PathLike) -> Path:
    """``path`` as a Path after checking its folder can be made and written to (InputError naming it), so
    a failing export stops before any work and leaves nothing behind."""
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: is a folder; expected a file name ending in {', '.join(USD_SUFFIXES)}")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile(dir=path.parent, prefix=f".{path.stem}.", suffix=".probe"):
            pass
    except OSError as error:
        raise InputError(f"{path}: cannot write there ({error.strerror or error})") from None
    return path


@dataclass
class UsdReport:
    """What ``export_usd`` wrote: path; format; units; points (rig vertices); faces; frames; fps;
    influences (elementSize of the skin primvars); expression_targets, larynx_targets, corrective_targets;
    split_targets: the ``_over``/``_under`` targets added for weights outside [0, 1] (``scene.usd.weights``);
    larynx_error_cm (the larynx targets' interpolation bound); larynx_scale: what they are scaled by;
    max_error_cm (the stored arrays against the rig over every frame, None if not checked); bytes; seconds."""

    path: Path | None
    format: str
    units: str
    points: int
    faces: int
    frames: int
    fps: float
    influences: int
    expression_targets: int
    larynx_targets: int
    corrective_targets: int
    split_targets: int
    larynx_error_cm: float
    larynx_scale: float
    max_error_cm: float | None = None
    bytes: int = 0
    seconds: float = 0.0

    def summary(self) -> str:
        lines = [f"wrote {self.path}: USD ({self.format}, UsdSkel), {self.points} points, {self.faces} faces, "
                 f"{self.frames} frames at {self.fps:g} fps, units {self.units}, {self.bytes / 1e6:.1f} MB "
                 f"in {self.seconds:.2f} s",
                 f"  skin: {self.influences} influences per point; blend shapes: {self.expression_targets} "
                 f"expressions, {self.larynx_targets} larynx (interpolation error {self.larynx_error_cm:.4f} cm), "
                 f"{self.corrective_targets} pose correctives"
                 + (f", {self.split_targets} for weights outside [0, 1]" if self.split_targets else "")]
        if self.max_error_cm is not None:
            lines.append(f"  max vertex error vs the rig over the clip: {self.max_error_cm:.4f} cm")
        return "\n".join(lines)


def time_codes(params: AnimationParams) -> np.ndarray:
    """The frames' USD time codes [T]: seconds times ``timeCodesPerSecond`` (= the clip's fps)."""
    return np.asarray(params.time, np.float64) * float(params.fps)


def export_usd(params: AnimationParams, rig: HeadNeckModel, path: str | os.PathLike | None, units: str = "cm",
               fmt: str | None = None, max_influences: int = 8, larynx_error_cm: float = USD_LARYNX_ERROR_CM,
               check: bool = False, source: str = "params", morph_normals: bool = True) -> UsdReport:
    """Write the clip ``params`` on ``rig`` as one UsdSkel stage at ``path`` (atomically; None: build only).

    Args:
        params, rig: the clip and the rig it drives (as for ``scene.gltf.export_glb``); the mesh, skin and
            targets come from ``scene.gltf.export_data``, so a per-person shape it applies is exported too.
        units: ``cm`` (metersPerUnit 0.01) or ``m``.
        fmt: usdc | usda | usdz; None: from ``path``'s suffix (usdc without a path).
        max_influences, morph_normals: as for the GLB.
        larynx_error_cm: the larynx targets' bound (half the GLB's by default, see USD_LARYNX_ERROR_CM).
        check: evaluate the stored arrays against ``rig(...)`` at every frame (``max_error_cm``).
        source: how to name the params in error messages.
    Raises:
        UsdMissing (an InputError) before any work when usd-core is absent; InputError for an unwritable
        path, an unknown suffix, or params of another rig, nothing written.
    """
    if units not in USD_UNITS:
        raise InputError(f"usd_units={units}: expected one of {', '.join(USD_UNITS)}")
    fmt = fmt or (usd_format(path) if path is not None else "usdc")
    if fmt not in USD_FORMATS:
        raise InputError(f"usd_format={fmt}: expected one of {', '.join(USD_FORMATS)}")
    require_usd()
    if path is not None:
        path = require_writable(path)
    started = timer.perf_counter()
    # Every number of the mesh comes from export_data (positions, targets, skin): a per-person shape that
    # params.npz may carry (the fitting work's ``shape_offset [V,3]``, the rig's template + offset) reaches
    # this file once export_data applies it for the GLB; nothing here reads the rig's template itself.
    export, influences, larynx, features = export_data(params, rig, max_influences, larynx_error_cm, source,
                                                       morph_normals)

    plain_targets = len(export.target_names)
    export, larynx_scale = within_unit_weights(export, len(rig.expression_names), len(larynx.taus))
    codes = time_codes(params)
    metadata = {"generator": "hackneck scene.usd (usd-core)", "source_units": "cm", "rig": str(params.rig or ""),
                "rig_checksum": str(params.rig_checksum or ""), "producers": json.dumps(params.producers),
                "target_names": list(export.target_names), "larynx_taus": [float(t) for t in larynx.taus],
                "larynx_target_scale": larynx_scale}
    stage = build_stage(export, rig, codes, float(params.fps), 1.0 / METRES_PER_UNIT[units], METRES_PER_UNIT[units],
                        metadata)
    size = 0
    if path is not None:
        with atomic_path(path) as tmp:
            write_stage(stage, tmp, fmt, Path(path).stem)
        size = path.stat().st_size
    report = UsdReport(
        path=path, format=fmt, units=units, points=rig.num_vertices, faces=len(rig.rig.faces), frames=len(params),
        fps=float(params.fps), influences=export.joints.shape[1], expression_targets=len(rig.expression_names),
        larynx_targets=len(larynx.taus), corrective_targets=len(features),
        split_targets=len(export.target_names) - plain_targets, larynx_error_cm=larynx.error_cm,
        larynx_scale=larynx_scale, bytes=size)
    report.seconds = timer.perf_counter() - started
    if check or influences.truncated:
        report.max_error_cm = export_error_cm(export, rig, params)
    return report


def write_stage(stage, target: Path, fmt: str, name: str) -> None:
    """Write ``stage`` to ``target`` as ``fmt``: the root layer exported as crate or text, or for usdz a
    crate layer (``<name>.usdc``) in a temporary folder packaged by ``UsdUtils.CreateNewUsdzPackage``."""
    from pxr import Sdf, UsdUtils

    layer = stage.GetRootLayer()
    if fmt != "usdz":
        if not layer.Export(str(target), args={"format": fmt}):
            raise InputError(f"{target}: USD could not write the {fmt} layer")
        return
    with tempfile.TemporaryDirectory() as folder:
        crate = Path(folder) / f"{name}.usdc"
        if not layer.Export(str(crate)):
            raise InputError(f"{crate}: USD could not write the layer to package")
        if not UsdUtils.CreateNewUsdzPackage(Sdf.AssetPath(str(crate)), str(target)):
            raise InputError(f"{target}: USD could not write the usdz package")
