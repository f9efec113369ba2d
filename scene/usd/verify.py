"""USD's own checks of a written file: every registered ``UsdValidation`` validator (usdSkel's and the usdz
package ones included), and the mesh as ``UsdSkel.BakeSkinning`` (USD's skinning) poses it."""
from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from scene.usd.stage import MESH


def validation_errors(path: str | os.PathLike) -> list[str]:
    """Every error (not warning) that all validators registered with ``UsdValidation`` report on the
    stage at ``path``, one line each ("<validator>: <message>")."""
    from pxr import Usd, UsdValidation

    registry = UsdValidation.ValidationRegistry()
    validators = registry.GetOrLoadAllValidators()
    stage = Usd.Stage.Open(str(path))
    context = UsdValidation.ValidationContext(validators)
    lines = []
    for error in context.Validate(stage):
        if error.HasNoError() or error.GetType() != UsdValidation.ValidationErrorType.Error:
            continue
        lines.append(f"{error.GetValidator().GetMetadata().name if error.GetValidator() else '?'}: "
                     f"{error.GetMessage()}")
    return lines


def baked_points(path: str | os.PathLike, frames) -> np.ndarray:
    """The mesh's points [F,N,3] (the file's units) at the time codes ``frames``, skinned by
    ``UsdSkel.BakeSkinning`` over those codes.  The file is read into an anonymous layer that takes the
    baked points and is not saved (the session layer would not do: its default timeCodesPerSecond, 24,
    rescales the times of what is written into it)."""
    from pxr import Gf, Sdf, Usd, UsdSkel

    stage = Usd.Stage.Open(Sdf.Layer.OpenAsAnonymous(str(Path(path))), Usd.Stage.LoadAll)
    frames = [float(f) for f in frames]
    if not UsdSkel.BakeSkinning(stage.Traverse(), Gf.Interval(min(frames), max(frames))):
        raise RuntimeError(f"{path}: UsdSkel.BakeSkinning failed")
    points = stage.GetPrimAtPath(MESH).GetAttribute("points")
    return np.array([np.asarray(points.Get(Usd.TimeCode(f)), np.float64) for f in frames])
