"""Write a rig in the HACK release's folder layout (and ICT-FaceKit's), to test the converter without the
real assets.  Weights are written unnormalised and the map as a 16-bit PNG, as a converter must cope."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from data.assets import RigData
from data.mesh_io import write_obj


def write_release(rig: RigData, hack_dir: Path, ict_dir: Path, extra_ict_vertices: int = 7) -> None:
    model = hack_dir / "model"
    model.mkdir(parents=True)
    write_obj(model / "000_generic_neutral_mesh_newuv.obj", rig.template, rig.faces, rig.uv_coords, rig.faces_uv)
    local = rig.joint_rest_local
    lengths = []
    for j in range(len(rig.joint_names)):
        children = [c for c, p in enumerate(rig.parents) if p == j]
        lengths.append(float(local[children[0], 1, 3]) if children else 10.0)
    bones = {}
    for j, name in enumerate(rig.joint_names):
        parent = int(rig.parents[j])
        head = local[j, :3, 3] - (np.array([0.0, lengths[parent], 0.0]) if parent >= 0 else 0.0)
        bones[str(name)] = {"matrix": local[j, :3, :3].tolist(), "head": head.tolist(), "length": lengths[j],
                            "parent": None if parent < 0 else str(rig.joint_names[parent])}
    (model / "bones_neutral.json").write_text(json.dumps(bones))
    scale = np.random.default_rng(0).uniform(0.5, 2.0, len(rig.template))
    np.save(model / "weight_map_smooth.npy", (rig.skin_weights * scale[:, None]).T.astype(np.float64))
    cv2.imwrite(str(model / "Lc_mid.png"), np.round(rig.larynx_maps[0] * 65535).astype(np.uint16))
    np.save(model / "ts_larynx.npy", rig.larynx_direction)
    faces = ict_dir / "FaceXModel"
    faces.mkdir(parents=True)
    extra = np.random.default_rng(1).normal(size=(extra_ict_vertices, 3))  # ICT has more vertices than HACK
    neutral = np.concatenate([rig.template, extra])
    write_obj(faces / "generic_neutral_mesh.obj", neutral, rig.faces)
    for name, delta in zip(rig.expression_names, rig.expression_deltas):
        write_obj(faces / f"{name}.obj", neutral + np.concatenate([delta, np.zeros_like(extra)]), rig.faces)
