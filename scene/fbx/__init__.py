"""FBX export through headless Blender (``export.py``) and Blender as a sampling tool (``blender.py``);
``blender_side.py`` is the half that runs inside Blender."""
from scene.fbx.blender import INSTALL_HINT, BlenderMissing, blender_executable, blender_vertices
from scene.fbx.export import FBX_UNITS, FbxReport, export_fbx

__all__ = ["FBX_UNITS", "INSTALL_HINT", "BlenderMissing", "FbxReport", "blender_executable", "blender_vertices",
           "export_fbx"]
