"""USD export: the clip as one animated UsdSkel stage (Omniverse, Houdini Solaris, Maya USD, Unreal's USD
stage, Apple's Quick Look through usdz).

    python -m scene.gltf source=params.npz out=anim.usdc|anim.usda|anim.usdz [usd_units=cm|m] [...]

- :mod:`scene.usd.stage`: the stage built from the GLB's arrays (``scene.gltf.export_data``);
- :mod:`scene.usd.export`: :func:`export_usd` (formats, units, atomic writing, usdz packaging);
- :mod:`scene.usd.verify`: USD's validators and ``UsdSkel.BakeSkinning`` on a written file.

Needs usd-core (``pxr``), imported only when exporting.
"""
from scene.usd.export import (
    INSTALL_HINT,
    USD_FORMATS,
    USD_LARYNX_ERROR_CM,
    USD_SUFFIXES,
    USD_UNITS,
    UsdMissing,
    UsdReport,
    export_usd,
    require_usd,
    time_codes,
    usd_format,
)
from scene.usd.stage import joint_paths, usd_name
from scene.usd.verify import baked_points, validation_errors

__all__ = ["INSTALL_HINT", "USD_FORMATS", "USD_LARYNX_ERROR_CM", "USD_SUFFIXES", "USD_UNITS", "UsdMissing",
           "UsdReport", "baked_points", "export_usd", "joint_paths", "require_usd", "time_codes", "usd_format",
           "usd_name", "validation_errors"]
