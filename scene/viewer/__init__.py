"""The web viewer: one self-contained ``viewer.html`` (three.js inlined, the clip's GLB embedded) that plays a
``params.npz`` offline from ``file://``, with tau and the joint angles drawn under the 3D view.

    from scene.viewer import build_viewer
    build_viewer("params.npz", None, "viewer.html")

The page exposes ``window.hackneck``: ``state()`` -> ``{time, frame, bones: {joint: [x, y, z, w]}, morphs:
{expression: weight}, tau, eta}`` (the last frame applied; each joint's rotation relative to its rest pose),
``seek(seconds)``, ``play()``, ``pause()``, and ``applyFrame(frame)`` / ``pushFrame(frame)`` for a live source
(a frame: ``{time, theta: [J][3] or bones, psi: [E] or morphs, tau, eta}``).  The three.js bundle is rebuilt
by ``scene/viewer/vendor/build.sh``.
"""
from scene.viewer.build import THREE_BUNDLE, ViewerReport, build_viewer, clip_header, glb_bytes, render_page

__all__ = ["THREE_BUNDLE", "ViewerReport", "build_viewer", "clip_header", "glb_bytes", "render_page"]
