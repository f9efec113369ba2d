"""Inference: hand it a facial capture, get the neck that goes with it.

    python infer.py                                    # the built-in demo take, shipped models
    python infer.py expressions=take.csv [out_dir=out/]
    python infer.py expressions=takes/ workers=2       # every take in a folder, one subfolder each
    python infer.py expressions=take.csv checkpoint=runs/larynx_transformer/<run>/checkpoints/last.pt \\
        head2neck=none swallow_at=[2.0,7.5] meshes=true export=[glb,mp4,html,fbx,usd] [rig=hack_rig.npz]
    python infer.py expressions=clip.mp4 [mirror=true]  # any face video (pip install ".[video]")
    python infer.py expressions=take.csv audio=take.mov # the voice's pitch moves the larynx too

Reads an expression recording (``data.expressions.read_expressions``: Live Link Face, ARKit or
HACK-named CSV, header-less 55-column CSV, ``.npy`` with ``fps=``, or a face video through
``motion.face``: MediaPipe's ARKit weights and head rotation on the video's timestamps), resamples it to one frame rate
(the larynx model's, else ``out_fps``, else the recording's) and computes, per frame:

- tau: the expression -> larynx transformer streamed over psi (``checkpoint``: ``default`` = the shipped
  model, ``none`` = the larynx rests, or a train.py checkpoint);
- swallows: a swallow template (``swallow_template``: ``default`` = the shipped one, or a template
  CSV from ``python -m motion.swallow``) inserted at ``swallow_at`` seconds (the demo take: at 6.2 s),
  blended as ``swallow_playback`` says;
- theta: the recording's head rotation (``HeadYaw, HeadPitch, HeadRoll``; conventions and options in
  ``motion/head2neck/__init__.py``) through the head -> cervical spine model (``head2neck``: ``default``,
  ``none`` or a checkpoint) in the bone frames of the rig; without recorded head rotation the neck rests;
- with the take's audio (``audio=``, or the file beside the take with its name; ``motion.voice``): F0 and
  a zero-mean voice term added to tau.

Everything goes into one folder, ``out_dir`` (default ``runs/infer/<time>/``), written whole or not at
all (a staging folder renamed into place): ``params.npz`` (``data.params``: the file ``motion.retarget``
and the exporters read), ``params.csv`` (a row per frame), ``plot.png`` (tau and eta with the swallows,
the joints' anatomical angles), ``meshes/frame_00000.ply ...`` with ``meshes=true``, ``anim.glb``
(``scene.gltf``: Blender, Unity, three.js) and ``preview.mp4`` (``scene.preview``) with
``export=[glb,mp4]``, ``viewer.html`` (``scene.viewer``) and ``anim.fbx`` (``scene.fbx``, through Blender)
with ``export=[html,fbx]``, ``anim.usdc`` (``scene.usd``: UsdSkel; ``usd_format=usda|usdz``, ``usd_units=cm|m``)
with ``export=[usd]``, ``face_frames.csv`` for a video.  A folder of takes gives one subfolder per
take, a summary table (``summary.csv``), and goes on past a take that fails, naming its reason.
"""
from __future__ import annotations

from base.cli import run_cli
from motion.pipeline.cli import run

__all__ = ["run"]

if __name__ == "__main__":
    run_cli("infer", run, doc=__doc__)
