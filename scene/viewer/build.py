"""Build ``viewer.html``: one self-contained, offline page (three.js inlined, the clip's GLB embedded as
base64, the clip's params as base64 float arrays) that plays a ``params.npz`` on its rig.

The page (``page.html`` + ``viewer.js`` in this package) plays, pauses and scrubs the clip, draws tau and
the joint angles under the 3D view, and exposes ``window.hackneck`` (``state()``, ``seek(s)``, ``play()``,
``pause()``, ``applyFrame(frame)``, ``pushFrame(frame)``, ``camera()``: the view's matrices) so tests and a
live source can drive it.
"""
from __future__ import annotations

import base64
import json
import os
import re
import time as timer
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from base.files import atomic_path
from data.params import AnimationParams, load_params
from models.rig import HeadNeckModel
from scene.gltf import build_glb, local_rotations, resolve_rig

HERE = Path(__file__).resolve().parent
VENDOR = HERE / "vendor"
THREE_BUNDLE = VENDOR / "three.min.js"
_PLACEHOLDER = re.compile(r"/\*@(\w+)@\*/")


@dataclass
class ViewerReport:
    """What :func:`build_viewer` wrote: path, frames, fps, bytes (the page), glb_bytes, seconds."""

    path: Path
    frames: int
    fps: float
    bytes: int
    glb_bytes: int
    seconds: float

    def summary(self) -> str:
        return (f"wrote {self.path}: {self.frames} frames at {self.fps:g} fps, {self.bytes / 1e6:.1f} MB "
                f"(GLB {self.glb_bytes / 1e6:.1f} MB) in {self.seconds:.2f} s")


def glb_bytes(params: AnimationParams, rig: HeadNeckModel, source: str = "params") -> bytes:
    """The binary glTF of the clip as :func:`scene.gltf.export_glb` writes it, built in memory
    (:func:`scene.gltf.build_glb`; the params' ``shape_offset`` applied to the base ``rig``)."""
    return build_glb(params, rig, check=False, source=source).raw


def _b64(array: np.ndarray, dtype) -> str:
    return base64.b64encode(np.ascontiguousarray(array, dtype=dtype).astype(dtype.newbyteorder("<")).tobytes()) \
        .decode("ascii")


def clip_header(params: AnimationParams, rig: HeadNeckModel, title: str = "") -> dict:
    """What the page needs besides the GLB: names, rest rotations, and the clip's frames (little-endian
    base64: time float64 [T], theta float32 [T*J*3], psi float32 [T*E], tau, eta float32 [T])."""
    rest = local_rotations(rig, np.eye(3)[None, None].repeat(rig.num_joints, axis=1))[0].astype(np.float64)
    return {
        "title": title, "fps": float(params.fps), "frames": len(params),
        "joints": list(params.joint_names), "expressions": list(params.expression_names),
        "rest": rest.tolist(),
        "data": {"time": _b64(params.time, np.dtype(np.float64)), "theta": _b64(params.theta, np.dtype(np.float32)),
                 "psi": _b64(params.psi, np.dtype(np.float32)), "tau": _b64(params.tau, np.dtype(np.float32)),
                 "eta": _b64(params.eta, np.dtype(np.float32))},
    }


def render_page(header: dict, glb: bytes, companion_glb: bytes = b"") -> str:
    """The html text: ``page.html`` with the three.js bundle, ``viewer.js``, the header and the GLBs inlined
    (the companion's empty when ``header`` has no ``companion``)."""
    # "<" escaped so that no "</script>" can end the JSON block early
    header_json = json.dumps(header, separators=(",", ":")).replace("<", "\\u003c")
    values = {
        "THREE": THREE_BUNDLE.read_text(encoding="utf-8"),
        "VIEWER": (HERE / "viewer.js").read_text(encoding="utf-8"),
        "HEADER": header_json,
        "GLB": base64.b64encode(glb).decode("ascii"),
        "COMPANION_GLB": base64.b64encode(companion_glb).decode("ascii"),
        "TITLE": (header.get("title") or "hackneck viewer").replace("&", "&amp;").replace("<", "&lt;"),
    }
    for name in ("THREE", "VIEWER"):
        if re.search(r"</script", values[name], re.IGNORECASE):
            raise ValueError(f"{name} holds '</script' and cannot be inlined")
    template = (HERE / "page.html").read_text(encoding="utf-8")
    # one pass: text substituted in is never scanned for placeholders again
    return _PLACEHOLDER.sub(lambda m: values[m.group(1)], template)


def build_viewer(source: str | os.PathLike | AnimationParams, rig: HeadNeckModel | None, out_path: str | os.PathLike,
                 glb: bytes | str | os.PathLike | None = None, title: str | None = None,
                 companion: tuple[AnimationParams, HeadNeckModel] | None = None) -> ViewerReport:
    """Write ``out_path`` (atomically): the viewer page of the clip ``source`` on ``rig``.

    Args:
        source: a params.npz path or the params themselves.
        rig: the rig they drive; None: the rig recorded in the params (``scene.characters.resolve_rig``).
        glb: the clip's GLB (bytes or a path, e.g. the ``anim.glb`` just written); None: built here.
        title: shown in the page (default the source's name).
        companion: another character's clip on the same clock and its rig (the human a giraffe's clip was
            retargeted from), shown to the left; ``state()`` reports it under ``companion``.
    """
    started = timer.perf_counter()
    if isinstance(source, AnimationParams):
        params, name = source, str(source.producers.get("source", "params"))
    else:
        params, name = load_params(source), str(source)
    if rig is None:
        rig = resolve_rig(params, name)
    if glb is None:
        glb = glb_bytes(params, rig, name)
    elif not isinstance(glb, (bytes, bytearray)):
        glb = Path(glb).read_bytes()
    header = clip_header(params, rig, title if title is not None else Path(name).name)
    companion_glb = b""
    if companion is not None:
        companion_params, companion_rig = companion
        if len(companion_params) != len(params) or not np.allclose(companion_params.time, params.time, atol=1e-9):
            raise ValueError(f"{name}: the companion's clip has other frame times than the clip's")
        header["companion"] = clip_header(companion_params, companion_rig, "")
        companion_glb = glb_bytes(companion_params, companion_rig, f"{name} (companion)")
    text = render_page(header, bytes(glb), companion_glb)
    out_path = Path(out_path)
    raw = text.encode("utf-8")
    with atomic_path(out_path) as tmp:
        tmp.write_bytes(raw)
    return ViewerReport(path=out_path, frames=len(params), fps=float(params.fps), bytes=len(raw),
                        glb_bytes=len(glb), seconds=timer.perf_counter() - started)
