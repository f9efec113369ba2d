"""FBX export through headless Blender (``export.py``, ``blender.py`` finds and runs Blender);
``blender_side.py`` is the half that runs inside Blender (its ``sample`` serves ``tests/blender_sampling.py``)."""
from scene.fbx.blender import INSTALL_HINT, BlenderMissing, blender_executable
from scene.fbx.export import FBX_UNITS, FbxReport, export_fbx

__all__ = ["FBX_UNITS", "INSTALL_HINT", "BlenderMissing", "FbxReport", "blender_executable", "export_fbx"]
