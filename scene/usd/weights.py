"""Blend-shape weights kept within [0, 1], the mesh unchanged.

USD does not clamp blend-shape weights (UsdSkel's skinning and Omniverse use them as they are), but
Blender's USD importer gives every shape key the slider range [0, 1] and clamps its value to it: a
larynx larger than the generic one (eta > 1), an expression weight outside [0, 1], and every pose
corrective (its weight is an entry of R - I, of either sign) would move wrongly there.  So:

- the larynx targets are stored scaled by the clip's largest larynx weight ``s`` (``L(s, tau_k)``),
  their weights divided by it;
- any other target whose weights leave [0, 1] keeps its name with the weight clipped to [0, 1], and
  gains ``<name>_over`` (the target times ``a``, weight ``max(w - 1, 0) / a``, ``a`` the clip's largest
  excess) and/or ``<name>_under`` (the target times ``-b``, weight ``max(-w, 0) / b``).

The three parts sum to ``w`` at every frame, and, being linear in ``w``, at every time between frames
too (USD interpolates weights linearly), so the mesh is the same as with the plain weights.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from scene.gltf import ExportData

SLACK = 1e-6     # weights within this of [0, 1] (float32 rounding) count as inside


def within_unit_weights(export: ExportData, first_larynx: int, larynx_count: int) -> tuple[ExportData, float]:
    """``export`` with every target's weights in [0, 1] (see the module), and the larynx scale ``s`` (1 when
    the larynx weights stay within 1).  Targets ``first_larynx .. first_larynx + larynx_count - 1`` are the
    larynx ones."""
    weights = export.morph_weights.astype(np.float64)
    targets = export.targets.astype(np.float64)
    normals = export.normal_targets.astype(np.float64)
    names = list(export.target_names)
    larynx = slice(first_larynx, first_larynx + larynx_count)
    scale = max(1.0, float(np.abs(weights[:, larynx]).max(initial=0.0)))
    if scale > 1.0:
        targets[larynx] *= scale
        if len(normals):
            normals[larynx] *= scale
        weights[:, larynx] /= scale
    extra_targets, extra_normals, extra_weights = [], [], []
    for k in range(len(names)):      # the larynx too: a negative eta would give it negative weights
        w = weights[:, k]
        excess, deficit = float(w.max(initial=0.0)) - 1.0, -float(w.min(initial=0.0))
        if excess <= SLACK and deficit <= SLACK:
            continue
        for size, sign, suffix, part in ((excess, 1.0, "over", np.maximum(w - 1.0, 0.0)),
                                         (deficit, -1.0, "under", np.maximum(-w, 0.0))):
            if size > SLACK:
                names.append(f"{names[k]}_{suffix}")
                extra_targets.append(targets[k] * sign * size)
                if len(normals):
                    extra_normals.append(normals[k] * sign * size)
                extra_weights.append(part / size)
        weights[:, k] = np.clip(w, 0.0, 1.0)
    if extra_targets:
        targets = np.concatenate([targets, np.array(extra_targets)])
        weights = np.concatenate([weights, np.array(extra_weights).T], axis=1)
        if len(normals):
            normals = np.concatenate([normals, np.array(extra_normals)])
    out = dataclasses.replace(export, targets=targets.astype(np.float32), normal_targets=normals.astype(np.float32),
                              target_names=names, morph_weights=weights.astype(np.float32))
    return out, scale
