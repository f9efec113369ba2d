"""``python -m motion.fit``: fit the rig to a capture (registered meshes or raw scans) and write its parameters.

    python -m motion.fit input=DIR kind=meshes [rig=hack_rig.npz] [units=cm] [fps=30] out_dir=OUT  # rig topology
    python -m motion.fit input=DIR kind=scans  [rig=hack_rig.npz] units=mm [fps=30] out_dir=OUT     # any topology
    python -m motion.fit input=DIR kind=meshes ... export=[glb,fbx,html,mp4,usd] [meshes=true]      # as infer.py
    python -m motion.fit input=take.npz kind=meshes out_dir=OUT      # an .npz holding vertices [T,V,3]
    python -m motion.fit input=DIR kind=scans units=mm fit_shape=true out_dir=OUT   # another person's shape

Input (``motion.fit.inputs``): ``kind=meshes``: a folder of OBJ or PLY files, one frame each in name order
(numbers compared as numbers: frame_2 before frame_10), or an ``.npz`` holding ``vertices [T,V,3]``, in the
rig's vertex order (a vertex-count mismatch is refused naming the file and both counts); ``kind=scans``: a
folder of PLY (ascii, binary little or big endian) or OBJ point clouds or meshes of any vertex count
(partial, holes, noise, stray points).  ``units`` (mm | cm | m) converts the capture to the rig's cm; a
capture more than 3x larger or smaller than the rig is refused naming the file and the likely units.  The
capture's frame is arbitrary: the fit finds the rig's placement in it.  ``fps`` is the capture's rate.

The fit (``models.fit``: ``fit_meshes`` / ``fit_scans``; its knobs under ``solver.*``, ``FitSettings``):
per frame the placement (x_capture = root_rotation @ x_rig + root_translation, cm), theta in the rig's bone
frames with theta[:, 0] (c7t1) held at zero (its rotation is the same motion as the placement and is folded
into it), psi and tau; per sequence eta and, with ``fit_shape=true``, a smooth offset of the rest mesh
(another person's head and neck).

Everything goes into ``out_dir``, written whole or not at all: ``params.npz`` (``data.params``, as infer.py
writes it, plus ``root_rotation``, ``root_translation``, ``fit_rms_mm`` and ``shape_offset``; ``head_rotation``
is the rig-frame head pose, the placement excluded), ``params.csv`` (a row per frame, with the residual and
the placement), ``plot.png`` (the residual over time, tau and eta, the joints), ``report.json`` (frames/s,
the worst frames, per joint how well the data determine it, the settings), ``meshes/`` with ``meshes=true``
and the exports with ``export=[...]`` (in the rig's frame, the fitted person's shape included: ``anim.glb``,
``preview.mp4``, ``viewer.html``, ``anim.fbx``, ``anim.usdc``), as infer.py writes them.  The log names the
joints the skin does not pin down.  The outputs feed ``train.py task=head2neck data=theta_seq data.path=<fits>`` and
``train.py task=larynx_transformer data=pairs data.path=<fits>`` (a folder of fit folders), ``motion.retarget
source=OUT/params.npz`` and every exporter.
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field
from pathlib import Path

from base.cli import REQUIRED, register_config, to_dataclass
from base.errors import InputError
from base.files import atomic_folder, require_new_folder
from base.progress import progress_bar
from base.stopwatch import StageSeconds
from data.assets import RigData
from data.procedural_rig import build_procedural_rig
from models.fit import FitSettings, fit_meshes, fit_scans
from models.rig import HeadNeckModel
from motion.fit.inputs import KINDS, UNITS_CM, read_capture
from motion.fit.outputs import fit_params, fit_report, plot_fit, summary_lines, write_report
from motion.pipeline.config import InferConfig
from motion.pipeline.models import Models
from motion.pipeline.outputs import write_outputs
from scene.fbx import blender_executable


@dataclass
class FitCli:
    """``python -m motion.fit`` settings (``configs/fit.yaml``); see the module docstring."""

    input: str = REQUIRED           # a folder of OBJ / PLY frames, or (kind=meshes) an .npz of vertices [T,V,3]
    kind: str = REQUIRED            # meshes (the rig's topology) | scans (any)
    out_dir: str = REQUIRED         # the output folder (new or empty)
    rig: str = "builtin"            # builtin | a rig file from python -m data.assets
    units: str = "cm"               # the capture's unit: mm | cm | m
    fps: float = 30.0               # the capture's frame rate
    fit_shape: bool = False         # fit the person's shape (a smooth offset of the rest mesh), as solver.fit_shape
    meshes: bool = False            # one posed mesh per frame in meshes/ (the rig's frame)
    mesh_format: str = "ply"        # ply | obj
    export: list[str] = field(default_factory=list)  # glb, mp4, html, fbx, usd (as infer.py)
    fbx_units: str = "cm"           # cm | m
    usd_format: str = "usdc"        # usdc | usda | usdz (anim.<usd_format>, scene.usd)
    usd_units: str = "cm"           # cm (metersPerUnit 0.01) | m
    plot: bool = True
    progress: bool = True           # progress bars while reading and fitting
    threads: int = 2
    solver: FitSettings = field(default_factory=FitSettings)   # models.fit's knobs

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ValueError(f"kind={self.kind}: expected one of {', '.join(KINDS)}")
        if self.units not in UNITS_CM:
            raise ValueError(f"units={self.units}: expected one of {', '.join(UNITS_CM)}")
        if not self.fps > 0:
            raise ValueError(f"fps={self.fps}: expected a positive frame rate")
        self.outputs()   # the outputs' settings are infer.py's and checked there (mesh_format, export, units)

    def outputs(self) -> InferConfig:
        """What to write besides the fit, as ``infer.py``'s settings (``motion.pipeline.outputs``)."""
        return InferConfig(meshes=self.meshes, mesh_format=self.mesh_format, export=list(self.export),
                           fbx_units=self.fbx_units, usd_format=self.usd_format, usd_units=self.usd_units,
                           plot=False)


register_config("fit_schema", FitCli)


def solver_settings(settings: FitCli) -> FitSettings:
    """The solver's settings: ``solver.*`` with ``fit_shape`` (either key turns the shape term on)."""
    solver = settings.solver
    values = {f.name: getattr(solver, f.name) for f in dataclasses.fields(solver)}
    values["fit_shape"] = bool(settings.fit_shape or solver.fit_shape)
    if isinstance(values.get("iterations"), list):
        values["iterations"] = tuple(values["iterations"])
    return FitSettings(**values)


def fitter(kind: str):
    """``models.fit.fit_meshes`` or ``fit_scans``."""
    return fit_meshes if kind == "meshes" else fit_scans


def name_frame(message: str, names: list[str]) -> str:
    """``message`` with the input file of the first ``frame <k>`` it mentions."""
    found = re.search(r"frame (\d+)", message)
    if found and int(found.group(1)) < len(names):
        return f"{message} (frame {found.group(1)} is {names[int(found.group(1))]})"
    return message


def rig_label(rig: str) -> str:
    return "builtin" if rig in ("", "builtin") else str(Path(rig).resolve())


def run(cfg) -> dict:
    """``python -m motion.fit``: read, fit, write ``out_dir`` whole; the report."""
    settings = to_dataclass(cfg, FitCli, where="motion.fit")
    if "fbx" in settings.export:
        blender_executable()   # before any work: one line saying how to install it, exit status 2
    out_dir = Path(settings.out_dir)
    require_new_folder(out_dir)
    solver, fit = solver_settings(settings), fitter(settings.kind)
    seconds = StageSeconds()
    with seconds.time("read"):
        rig = build_procedural_rig() if settings.rig in ("", "builtin") else RigData.load(settings.rig)
        with progress_bar(desc="reading", unit="frame", disable=not settings.progress) as bar:
            capture = read_capture(settings.input, settings.kind, settings.units, rig.template,
                                   progress=lambda k: bar.update(k - bar.n))
    with seconds.time("rig"):
        model = HeadNeckModel(rig)   # after reading: bad input is refused before the rig's set-up

    with seconds.time("fit"), progress_bar(total=len(capture), desc="fitting", unit="frame",
                                           disable=not settings.progress) as bar:
        try:
            result = fit(model, capture.frames, solver, progress=lambda k: bar.update(k - bar.n))
        except InputError as e:   # the solver names a frame by its index: name its file too
            raise InputError(name_frame(str(e), capture.names)) from None

    producers = {"tool": "motion.fit", "fit": f"models.fit.{fit.__name__}", "source": capture.source,
                 "kind": settings.kind, "units": settings.units, "fit_shape": solver.fit_shape}
    outputs = settings.outputs()
    lines = []
    with atomic_folder(out_dir) as staging:
        with seconds.time("write"):
            params = fit_params(result, model, float(settings.fps), rig_label(settings.rig), producers)
            output_seconds = write_outputs(outputs, Models(rig=model, rig_name=rig_label(settings.rig)), params,
                                           staging, announce=lines.append, out_dir=out_dir)
        report = fit_report(params, result, model, capture.names, seconds, {
            **{k: v for k, v in dataclasses.asdict(settings).items() if k != "solver"},
            "solver": dataclasses.asdict(solver)})
        report["output_seconds"] = {k: round(v, 3) for k, v in output_seconds.items()}
        if settings.plot:
            plot_fit(staging / "plot.png", params, model, report["worst_frames"])
        write_report(staging / "report.json", report)
    print("\n".join(summary_lines(report) + lines + [f"wrote {out_dir}: params.npz, params.csv, report.json"
                                                     + (", plot.png" if settings.plot else "")]))
    return report


__all__ = ["FitCli", "run", "solver_settings"]
