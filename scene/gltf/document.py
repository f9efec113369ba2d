"""The binary glTF file: the document and its buffer built from :class:`scene.gltf.clip.ExportData`, the
export report.
"""
from __future__ import annotations

import json
import os
import time as timer
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pygltflib as gl

from base.files import atomic_path
from data.params import AnimationParams
from models.rig import HeadNeckModel
from scene.characters import person_rig
from scene.gltf.clip import ExportData, export_data, export_error_cm
from scene.gltf.morphs import DEFAULT_LARYNX_ERROR_CM, LarynxTargets

SKIN_COLOUR = [0.80, 0.62, 0.52, 1.0]


@dataclass
class ExportReport:
    """What an export wrote and how faithful it is.

    path (None until written, :func:`write_glb`); vertices (glTF) / rig_vertices; triangles; frames; fps;
    influences (per vertex in the file) and truncated (vertices that lost weight); expression_targets,
    larynx_targets, corrective_targets; tau_range (low, high); larynx_error_cm (the interpolation bound);
    max_error_cm: the largest vertex error over all frames of the file's own data (skin + morphs, float32)
    against the rig's forward pass
    (None if not checked); bytes; seconds.
    """

    path: Path | None
    vertices: int
    rig_vertices: int
    triangles: int
    frames: int
    fps: float
    influences: int
    truncated: int
    expression_targets: int
    larynx_targets: int
    corrective_targets: int
    tau_range: tuple[float, float]
    larynx_error_cm: float
    max_error_cm: float | None = None
    bytes: int = 0
    seconds: float = 0.0

    def summary(self) -> str:
        lines = [
            f"wrote {self.path}: {self.vertices} vertices ({self.rig_vertices} rig vertices, split at UV seams), "
            f"{self.triangles} triangles, {self.frames} frames at {self.fps:g} fps, {self.bytes / 1e6:.1f} MB "
            f"in {self.seconds:.2f} s",
            f"  skin: {self.influences} influences per vertex"
            + (f" ({self.truncated} vertices had more and were renormalised)" if self.truncated else ""),
            f"  morph targets: {self.expression_targets} expressions, {self.larynx_targets} larynx "
            f"(tau {self.tau_range[0]:+.4f} .. {self.tau_range[1]:+.4f}, interpolation error "
            f"{self.larynx_error_cm:.4f} cm), {self.corrective_targets} pose correctives",
        ]
        if self.max_error_cm is not None:
            lines.append(f"  max vertex error vs the rig over the clip: {self.max_error_cm:.4f} cm")
        return "\n".join(lines)


@dataclass
class _Builder:
    """Buffer views and accessors of one binary buffer."""

    gltf: gl.GLTF2
    chunks: list = field(default_factory=list)
    length: int = 0

    def view(self, data: np.ndarray, target: int | None = None) -> int:
        raw = np.ascontiguousarray(data).tobytes()
        pad = (-self.length) % 4
        if pad:
            self.chunks.append(b"\x00" * pad)
            self.length += pad
        self.gltf.bufferViews.append(gl.BufferView(buffer=0, byteOffset=self.length, byteLength=len(raw),
                                                   target=target))
        self.chunks.append(raw)
        self.length += len(raw)
        return len(self.gltf.bufferViews) - 1

    def accessor(self, data: np.ndarray, kind: str, target: int | None = None, bounds: bool = False,
                 name: str | None = None) -> int:
        data = np.asarray(data)
        component = {np.dtype(np.float32): gl.FLOAT, np.dtype(np.uint8): gl.UNSIGNED_BYTE,
                     np.dtype(np.uint16): gl.UNSIGNED_SHORT, np.dtype(np.uint32): gl.UNSIGNED_INT}[data.dtype]
        accessor = gl.Accessor(bufferView=self.view(data, target), componentType=component, count=data.shape[0],
                               type=kind, name=name)
        self._bounds(accessor, data, kind, bounds)
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1

    def sparse_vec3(self, data: np.ndarray, name: str | None = None, bounds: bool = True) -> int:
        """A float32 VEC3 morph-target accessor [V,3], sparse when few rows are non-zero."""
        data = np.asarray(data, np.float32)
        rows = np.flatnonzero(np.abs(data).max(1) > 0)
        if len(rows) * 16 >= data.size * 4 * 0.75:
            return self.accessor(data, gl.VEC3, gl.ARRAY_BUFFER, bounds=bounds, name=name)
        accessor = gl.Accessor(componentType=gl.FLOAT, count=len(data), type=gl.VEC3, name=name, byteOffset=None)
        if len(rows):
            index_type = np.uint16 if len(data) < 2**16 else np.uint32
            accessor.sparse = gl.Sparse(
                count=len(rows),
                indices=gl.AccessorSparseIndices(bufferView=self.view(rows.astype(index_type)),
                                                 componentType=gl.UNSIGNED_SHORT if index_type is np.uint16
                                                 else gl.UNSIGNED_INT),
                values=gl.AccessorSparseValues(bufferView=self.view(data[rows])))
        self._bounds(accessor, data, gl.VEC3, bounds)
        self.gltf.accessors.append(accessor)
        return len(self.gltf.accessors) - 1

    @staticmethod
    def _bounds(accessor: gl.Accessor, data: np.ndarray, kind: str, bounds: bool) -> None:
        if not bounds:
            accessor.min, accessor.max = None, None
            return
        flat = data.reshape(len(data), -1) if kind != gl.SCALAR else data.reshape(-1, 1)
        # float32 extremes as Python floats: exact, so the validator's min/max check holds
        accessor.min = [float(v) for v in flat.min(0)]
        accessor.max = [float(v) for v in flat.max(0)]

    def blob(self) -> bytes:
        raw = b"".join(self.chunks)
        return raw + b"\x00" * ((-len(raw)) % 4)


def build_gltf(export: ExportData, rig: HeadNeckModel, params: AnimationParams, extras: dict | None = None) -> gl.GLTF2:
    """The glTF document (with its binary blob set) of ``export``."""
    data = rig.rig
    gltf = gl.GLTF2(asset=gl.Asset(version="2.0", generator="hackneck scene.gltf (pygltflib)",
                                   extras=extras or {}))
    b = _Builder(gltf)
    split = export.split
    position = b.accessor(export.positions, gl.VEC3, gl.ARRAY_BUFFER, bounds=True, name="POSITION")
    normal = b.accessor(export.normals, gl.VEC3, gl.ARRAY_BUFFER, name="NORMAL")
    uv = np.stack([split.uv[:, 0], 1.0 - split.uv[:, 1]], axis=1).astype(np.float32)
    texcoord = b.accessor(uv, gl.VEC2, gl.ARRAY_BUFFER, name="TEXCOORD_0")
    attributes = gl.Attributes(POSITION=position, NORMAL=normal, TEXCOORD_0=texcoord)
    joint_type = np.uint8 if rig.num_joints <= 256 else np.uint16
    for slot in range(export.joints.shape[1] // 4):
        columns = slice(4 * slot, 4 * slot + 4)
        joint_slots = export.joints[:, columns].astype(joint_type)
        setattr(attributes, f"JOINTS_{slot}", b.accessor(joint_slots, gl.VEC4, gl.ARRAY_BUFFER, name=f"JOINTS_{slot}"))
        setattr(attributes, f"WEIGHTS_{slot}",
                b.accessor(export.weights[:, columns], gl.VEC4, gl.ARRAY_BUFFER, name=f"WEIGHTS_{slot}"))
    index_type = np.uint16 if len(export.positions) < 2**16 - 1 else np.uint32
    indices = b.accessor(split.triangles.reshape(-1).astype(index_type), gl.SCALAR, gl.ELEMENT_ARRAY_BUFFER,
                         name="indices")
    targets = [{"POSITION": b.sparse_vec3(target, name=name)} for target, name in zip(export.targets,
                                                                                      export.target_names)]
    for target, normal in zip(targets, export.normal_targets):
        target["NORMAL"] = b.sparse_vec3(normal, bounds=False)
    gltf.materials.append(gl.Material(name="skin", pbrMetallicRoughness=gl.PbrMetallicRoughness(
        baseColorFactor=SKIN_COLOUR, metallicFactor=0.0, roughnessFactor=0.6)))
    primitive = gl.Primitive(attributes=attributes, indices=indices, material=0, mode=gl.TRIANGLES,
                             targets=targets)
    gltf.meshes.append(gl.Mesh(name="head_neck", primitives=[primitive],
                               weights=[float(w) for w in export.morph_weights[0]],
                               extras={"targetNames": export.target_names,
                                       "rig_vertex_index": [int(i) for i in split.rig_index]}))

    # Nodes: 0 the skeleton's root, 1..J the joints, J+1 the skinned mesh (at the scene root).
    joints = list(range(1, rig.num_joints + 1))
    gltf.nodes.append(gl.Node(name="skeleton", children=[1 + j for j, p in enumerate(rig.parents) if p < 0]))
    for j, name in enumerate(data.joint_names):
        children = [1 + c for c, p in enumerate(rig.parents) if p == j]
        gltf.nodes.append(gl.Node(name=str(name), translation=[float(v) for v in export.translations[j]],
                                  rotation=[float(v) for v in export.rotations[0, j]], children=children or None))
    mesh_node = len(gltf.nodes)
    gltf.nodes.append(gl.Node(name="head_neck", mesh=0, skin=0))
    inverse_bind = np.transpose(export.inverse_bind, (0, 2, 1)).reshape(-1, 16)   # column-major
    gltf.skins.append(gl.Skin(name="cervical_spine", joints=joints, skeleton=0,
                              inverseBindMatrices=b.accessor(inverse_bind.astype(np.float32), gl.MAT4)))
    gltf.scenes.append(gl.Scene(name="hackneck", nodes=[0, mesh_node]))
    gltf.scene = 0

    times = b.accessor(export.times, gl.SCALAR, bounds=True, name="time")
    samplers, channels = [], []
    for j in range(rig.num_joints):
        samplers.append(gl.AnimationSampler(input=times, interpolation=gl.ANIM_LINEAR,
                                            output=b.accessor(export.rotations[:, j], gl.VEC4)))
        channels.append(gl.AnimationChannel(sampler=len(samplers) - 1,
                                            target=gl.AnimationChannelTarget(node=joints[j], path="rotation")))
    samplers.append(gl.AnimationSampler(input=times, interpolation=gl.ANIM_LINEAR,
                                        output=b.accessor(export.morph_weights.reshape(-1), gl.SCALAR)))
    channels.append(gl.AnimationChannel(sampler=len(samplers) - 1,
                                        target=gl.AnimationChannelTarget(node=mesh_node, path="weights")))
    gltf.animations.append(gl.Animation(name="clip", samplers=samplers, channels=channels,
                                        extras={"fps": float(params.fps)}))
    blob = b.blob()
    gltf.buffers.append(gl.Buffer(byteLength=len(blob)))
    gltf.set_binary_blob(blob)
    return gltf


def gltf_extras(params: AnimationParams, larynx: LarynxTargets) -> dict:
    """The file's ``asset.extras``: units and axes, the clip's rate, its rig and producers (JSON with sorted
    keys, as ``params.npz`` stores them: the same file from the params in memory or read back), the larynx
    nodes."""
    return {"units": "metre", "source_units": "cm", "up": "+y", "forward": "+z", "fps": float(params.fps),
            "rig": params.rig, "rig_checksum": params.rig_checksum,
            "producers": json.dumps(params.producers, sort_keys=True),
            "larynx_taus": [float(t) for t in larynx.taus]}


@dataclass
class Glb:
    """One clip's binary glTF, built in memory (:func:`build_glb`): ``raw`` the file's bytes, ``report`` what
    it holds (``path`` None until :func:`write_glb`)."""

    raw: bytes
    report: ExportReport


def build_glb(params: AnimationParams, rig: HeadNeckModel, max_influences: int = 8,
              larynx_error_cm: float = DEFAULT_LARYNX_ERROR_CM, check: bool = True, source: str = "params",
              morph_normals: bool = True) -> Glb:
    """The clip ``params`` on ``rig`` as one animated binary glTF, in memory: what :func:`export_glb`
    writes, and what the viewer page embeds and Blender converts to FBX (built once per take).

    Args:
        params: the per-frame inputs (``data.params.AnimationParams``) in the rig's bone frames.
        rig: the rig they drive (the base rig: a fitted ``params.shape_offset`` is added to its template here,
            ``scene.characters.person_rig``).
        max_influences: 8 (JOINTS_0 + JOINTS_1) or 4 (engines limited to four; costs the reported error).
        larynx_error_cm: bound on the larynx morph-target interpolation error.
        check: evaluate the stored data at every frame against ``rig(...)`` (``ExportReport.max_error_cm``);
            always done when vertices lose influences.
        source: how to name the params in error messages (their file).
        morph_normals: store each morph target's change of the normals (for viewers' shading; about
            doubles the file; Blender recomputes normals and ignores them).
    """
    started = timer.perf_counter()
    export, influences, larynx, features = export_data(params, rig, max_influences, larynx_error_cm, source,
                                                       morph_normals)
    raw = b"".join(build_gltf(export, rig, params, gltf_extras(params, larynx)).save_to_bytes())
    report = ExportReport(
        path=None, vertices=len(export.positions), rig_vertices=rig.num_vertices,
        triangles=len(export.split.triangles), frames=len(params), fps=float(params.fps),
        influences=export.joints.shape[1], truncated=influences.truncated,
        expression_targets=len(rig.expression_names), larynx_targets=len(larynx.taus),
        corrective_targets=len(features), tau_range=(float(np.min(params.tau)), float(np.max(params.tau))),
        larynx_error_cm=larynx.error_cm, bytes=len(raw))
    report.seconds = timer.perf_counter() - started
    if check or influences.truncated:  # dropping influences always reports what it costs
        report.max_error_cm = export_error_cm(export, person_rig(rig, params, source), params)
    return Glb(raw, report)


def write_glb(glb: Glb, path: str | os.PathLike) -> ExportReport:
    """Write ``glb`` at ``path`` (atomically); its report, with the path and the seconds writing took added."""
    started = timer.perf_counter()
    path = Path(path)
    with atomic_path(path) as tmp:
        tmp.write_bytes(glb.raw)
    return replace(glb.report, path=path, seconds=glb.report.seconds + timer.perf_counter() - started)


def export_glb(params: AnimationParams, rig: HeadNeckModel, path: str | os.PathLike, max_influences: int = 8,
               larynx_error_cm: float = DEFAULT_LARYNX_ERROR_CM, check: bool = True, source: str = "params",
               morph_normals: bool = True) -> ExportReport:
    """Write the clip ``params`` on ``rig`` as one animated ``.glb`` at ``path`` (atomically): :func:`build_glb`
    (its arguments) then :func:`write_glb`.  Returns the ExportReport (``summary()`` prints it)."""
    return write_glb(build_glb(params, rig, max_influences, larynx_error_cm, check, source, morph_normals), path)
