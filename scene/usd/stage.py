"""The UsdSkel stage built from :class:`scene.gltf.ExportData` (the arrays the GLB stores): the mesh on the
rig's own polygons, the skeleton, skin, blend shapes and the animation.

Layout (``/hackneck`` is the default prim)::

    /hackneck               SkelRoot, SkelBindingAPI (skel:skeleton, skel:animationSource)
      Skeleton              Skeleton: joints "c7t1", "c7t1/c6c7", ... (HACK's chain), bind + rest transforms
        Animation           SkelAnimation: translations (constant), rotations and blendShapeWeights (sampled)
      head_neck             Mesh, SkelBindingAPI: skel:jointIndices/jointWeights (vertex, elementSize 4|8),
                            skel:blendShapes + skel:blendShapeTargets, primvars:st, normals
        <target>            BlendShape: offsets (+ normalOffsets), pointIndices when sparse
      Looks/skin            Material (UsdPreviewSurface, the GLB's skin colour)

Matrices: ours act on column vectors (``p' = M p``), USD's on row vectors (``p' = p M``), so each is
stored transposed.  UsdSkel skins as glTF does (linear blend skinning of the blend-shaped points with
``bind^-1``; UsdSkel schema docs, "Skinning"), and does not clamp blend-shape weights.
"""
from __future__ import annotations

import re

import numpy as np

from data.mesh_io import triangulate
from models.rig import HeadNeckModel
from scene.gltf import SKIN_COLOUR, ExportData

ROOT = "/hackneck"
SKELETON = f"{ROOT}/Skeleton"
ANIMATION = f"{SKELETON}/Animation"
MESH = f"{ROOT}/head_neck"


def usd_name(name: str) -> str:
    """A valid USD prim name (and blend-shape token) for a target name: ``+``/``-`` as ``p``/``m``, other
    characters outside [A-Za-z0-9_] as ``_``; ``larynx_tau+0.01000`` -> ``larynx_tau_p0_01000``."""
    name = re.sub(r"([+-])(?=\d)", lambda m: "_p" if m.group(1) == "+" else "_m", name)
    name = re.sub(r"[^A-Za-z0-9_]", "_", name)
    name = re.sub(r"__+", "_", name)
    return name if re.match(r"[A-Za-z_]", name) else f"_{name}"


def joint_paths(names, parents) -> list[str]:
    """UsdSkel joint paths ("c7t1", "c7t1/c6c7", ...) of joints listed parents first."""
    paths: list[str] = []
    for name, parent in zip(names, parents):
        paths.append(str(name) if parent < 0 else f"{paths[parent]}/{name}")
    return paths


def rig_vertex_rows(export: ExportData) -> np.ndarray:
    """For each rig vertex, one row of the export's seam-split arrays holding it [N] (the split copies of a
    vertex share its position, normal, skin and targets)."""
    index = export.split.rig_index
    rows = np.empty(int(index.max()) + 1, np.int64)
    rows[index[::-1]] = np.arange(len(index))[::-1]
    return rows


def polygons(rig: HeadNeckModel, export: ExportData) -> tuple[np.ndarray, np.ndarray | None]:
    """The rig's faces [F,k] wound as the export's triangles (counter-clockwise outside, USD's right-handed
    default), and their UV indices [F,k] (None when the rig has only per-vertex UVs)."""
    faces = np.asarray(rig.rig.faces, np.int64)
    split = export.split
    flip = not np.array_equal(split.rig_index[split.triangles], triangulate(faces))
    data = rig.rig
    uv_faces = np.asarray(data.faces_uv, np.int64) \
        if data.faces_uv.size and data.uv_coords.size and data.faces_uv.shape == data.faces.shape else None
    if flip:
        faces = faces[:, ::-1]
        uv_faces = None if uv_faces is None else uv_faces[:, ::-1]
    return np.ascontiguousarray(faces), None if uv_faces is None else np.ascontiguousarray(uv_faces)


def _sparse_rows(*deltas: np.ndarray) -> np.ndarray | None:
    """Row indices where any of ``deltas`` [N,3] is non-zero; None when dense storage is smaller."""
    nonzero = np.zeros(len(deltas[0]), bool)
    for d in deltas:
        nonzero |= np.abs(d).max(1) > 0
    rows = np.flatnonzero(nonzero)
    return None if len(rows) * 16 >= len(nonzero) * 12 * 0.75 else rows


def build_stage(export: ExportData, rig: HeadNeckModel, time_codes: np.ndarray, fps: float, scale: float,
                metres_per_unit: float, metadata: dict):
    """An in-memory ``Usd.Stage`` of the clip.

    export: the GLB's arrays (metres); time_codes [T] of the frames; fps: timeCodesPerSecond; scale: units
    per metre of the stored numbers (100 for cm); metres_per_unit: the stage's metersPerUnit;
    metadata: the layer's customLayerData.
    """
    from pxr import Gf, Sdf, Usd, UsdGeom, UsdShade, UsdSkel, Vt

    stage = Usd.Stage.CreateInMemory()
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, metres_per_unit)
    stage.SetTimeCodesPerSecond(fps)
    stage.SetFramesPerSecond(fps)
    stage.SetStartTimeCode(float(time_codes[0]))
    stage.SetEndTimeCode(float(time_codes[-1]))
    stage.GetRootLayer().customLayerData = {
        key: (Vt.StringArray([str(v) for v in value]) if value and isinstance(value[0], str) else
              Vt.DoubleArray([float(v) for v in value])) if isinstance(value, list) else value
        for key, value in metadata.items()}

    root = UsdSkel.Root.Define(stage, ROOT)
    stage.SetDefaultPrim(root.GetPrim())
    Usd.ModelAPI(root.GetPrim()).SetKind("component")

    # skeleton: bind = the joints' rest world matrices, rest = their local ones
    names = [str(n) for n in rig.rig.joint_names]
    paths = joint_paths(names, rig.parents)
    bind = np.linalg.inv(export.inverse_bind.astype(np.float64))
    bind[:, :3, 3] *= scale
    bind[:, 3] = (0.0, 0.0, 0.0, 1.0)
    rest = np.array([bind[j] if p < 0 else np.linalg.inv(bind[p]) @ bind[j] for j, p in enumerate(rig.parents)])
    skeleton = UsdSkel.Skeleton.Define(stage, SKELETON)
    skeleton.CreateJointsAttr(Vt.TokenArray(paths))
    skeleton.CreateJointNamesAttr(Vt.TokenArray(names))
    skeleton.CreateBindTransformsAttr(Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(bind.transpose(0, 2, 1))))
    skeleton.CreateRestTransformsAttr(Vt.Matrix4dArray.FromNumpy(np.ascontiguousarray(rest.transpose(0, 2, 1))))

    # animation: the GLB's local rotations (x, y, z, w: GfQuatf's memory order) and morph weights
    tokens = [usd_name(n) for n in export.target_names]
    animation = UsdSkel.Animation.Define(stage, ANIMATION)
    animation.CreateJointsAttr(Vt.TokenArray(paths))
    animation.CreateTranslationsAttr(Vt.Vec3fArray.FromNumpy(
        (export.translations.astype(np.float64) * scale).astype(np.float32)))
    animation.CreateScalesAttr(Vt.Vec3hArray([Gf.Vec3h(1, 1, 1)] * len(paths)))
    animation.CreateBlendShapesAttr(Vt.TokenArray(tokens))
    rotations = animation.CreateRotationsAttr()
    weights = animation.CreateBlendShapeWeightsAttr()
    for t, code in enumerate(time_codes):
        time = Usd.TimeCode(float(code))
        rotations.Set(Vt.QuatfArray.FromNumpy(np.ascontiguousarray(export.rotations[t])), time)
        weights.Set(Vt.FloatArray.FromNumpy(np.ascontiguousarray(export.morph_weights[t])), time)
    root_binding = UsdSkel.BindingAPI.Apply(root.GetPrim())
    root_binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    skeleton_binding = UsdSkel.BindingAPI.Apply(skeleton.GetPrim())
    skeleton_binding.CreateAnimationSourceRel().SetTargets([animation.GetPath()])

    # mesh on the rig's polygons, one point per rig vertex
    rows = rig_vertex_rows(export)
    faces, uv_faces = polygons(rig, export)
    points = (export.positions[rows].astype(np.float64) * scale).astype(np.float32)
    mesh = UsdGeom.Mesh.Define(stage, MESH)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(points))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(len(faces), faces.shape[1], np.int32)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(faces.reshape(-1).astype(np.int32)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(export.normals[rows])))
    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(*map(float, points.min(0))), Gf.Vec3f(*map(float, points.max(0)))]))
    primvars = UsdGeom.PrimvarsAPI(mesh)
    if uv_faces is not None:
        st = primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(rig.rig.uv_coords, np.float32)))
        st.SetIndices(Vt.IntArray.FromNumpy(uv_faces.reshape(-1).astype(np.int32)))
    else:
        st = primvars.CreatePrimvar("st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.vertex)
        st.Set(Vt.Vec2fArray.FromNumpy(np.asarray(rig.rig.vertex_uv, np.float32)))

    binding = UsdSkel.BindingAPI.Apply(mesh.GetPrim())
    binding.CreateSkeletonRel().SetTargets([skeleton.GetPath()])
    # Redundant for UsdSkel (the skeleton's animationSource binds it), but early usdz viewers (iOS 13's
    # Quick Look) looked for it on the skinned mesh (noted in pkanyuk/PkUsdUtils' usdSkelAppleFixup).
    binding.CreateAnimationSourceRel().SetTargets([animation.GetPath()])
    size = export.joints.shape[1]
    binding.CreateJointIndicesPrimvar(False, size).Set(Vt.IntArray.FromNumpy(
        export.joints[rows].reshape(-1).astype(np.int32)))
    binding.CreateJointWeightsPrimvar(False, size).Set(Vt.FloatArray.FromNumpy(
        np.ascontiguousarray(export.weights[rows].reshape(-1))))
    binding.CreateGeomBindTransformAttr(Gf.Matrix4d(1.0))

    # blend shapes: the GLB's targets (+ their normal changes) on the rig's vertices
    targets = []
    for k, token in enumerate(tokens):
        shape = UsdSkel.BlendShape.Define(stage, f"{MESH}/{token}")
        offsets = (export.targets[k, rows].astype(np.float64) * scale).astype(np.float32)
        normal_offsets = export.normal_targets[k, rows] if len(export.normal_targets) else None
        keep = _sparse_rows(offsets, *([] if normal_offsets is None else [normal_offsets]))
        if keep is not None:
            offsets = offsets[keep]
            normal_offsets = None if normal_offsets is None else normal_offsets[keep]
            shape.CreatePointIndicesAttr(Vt.IntArray.FromNumpy(keep.astype(np.int32)))
        shape.CreateOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(offsets)))
        if normal_offsets is not None:
            shape.CreateNormalOffsetsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(normal_offsets)))
        targets.append(shape.GetPath())
    binding.CreateBlendShapesAttr(Vt.TokenArray(tokens))
    binding.CreateBlendShapeTargetsRel().SetTargets(targets)

    # material
    UsdGeom.Scope.Define(stage, f"{ROOT}/Looks")
    material = UsdShade.Material.Define(stage, f"{ROOT}/Looks/skin")
    shader = UsdShade.Shader.Define(stage, f"{ROOT}/Looks/skin/surface")
    shader.CreateIdAttr("UsdPreviewSurface")
    shader.CreateInput("diffuseColor", Sdf.ValueTypeNames.Color3f).Set(Gf.Vec3f(*SKIN_COLOUR[:3]))
    shader.CreateInput("roughness", Sdf.ValueTypeNames.Float).Set(0.6)
    shader.CreateInput("metallic", Sdf.ValueTypeNames.Float).Set(0.0)
    material.CreateSurfaceOutput().ConnectToSource(shader.ConnectableAPI(), "surface")
    UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim()).Bind(material)
    return stage
