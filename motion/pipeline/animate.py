"""One capture to animation parameters: read the take, run the larynx and neck models, insert swallows."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from base.cli import as_list
from base.errors import InputError
from base.stopwatch import StageSeconds
from base.timebase import GAP_SECONDS, fill_held, grid_segments
from data.demo_take import DEMO_SOURCE, SWALLOW_ONSET, demo_take
from data.expressions import EXPRESSION_NAMES, ExpressionTrack, arkit_name, read_expressions
from data.params import AnimationParams, rig_checksum
from models.head2neck import predict_theta
from models.larynx import predict_tau
from models.pretrained import pretrained_path
from motion.face import read_face_video
from motion.face.frames import VIDEO_SUFFIXES
from motion.head2neck import head_rotations_from_ypr, recentered
from motion.pipeline.config import InferConfig
from motion.pipeline.models import Models
from motion.swallow import insert_swallows, read_template
from motion.voice import load_voice, voice_on_frames

# Expressions no ARKit capture has (ICT's cheekRaiser_L/R): their absence is a note, not an error.
NEVER_IN_ARKIT = tuple(name for name in EXPRESSION_NAMES if arkit_name(name) is None)


def read_take(cfg: InferConfig, path: str | None, announce=print) -> ExpressionTrack:
    """The recording at ``path`` (or the demo take), refusing one that lacks ARKit expression columns
    unless ``allow_missing``.  A video (``VIDEO_SUFFIXES``) goes through the face stage (``motion.face``:
    ``face_model``, ``face_smoothing``, ``face_max_gap``); ``mirror`` swaps left and right (selfie footage)."""
    if path is None:
        return demo_take()
    if Path(path).suffix.lower() in VIDEO_SUFFIXES:
        track = read_face_video(path, cfg.face_model, cfg.face_smoothing, cfg.face_max_gap, announce=announce)
    else:
        track = read_expressions(path, fps=cfg.fps, timecode_fps=cfg.timecode_fps)
    if cfg.mirror:
        track = track.mirrored()
    lacking = [name for name in track.missing if name not in NEVER_IN_ARKIT]
    if lacking and not cfg.allow_missing:
        columns = sorted({arkit_name(name) or name for name in lacking})
        raise InputError(f"{path}: no column for {len(lacking)} of the {len(EXPRESSION_NAMES)} expressions "
                         f"({', '.join(columns[:8])}{', ...' if len(columns) > 8 else ''}); expected a full "
                         f"ARKit / HACK capture, or allow_missing=true to run with them at 0")
    return track


def segmented_tau(model, psi: np.ndarray, segment: np.ndarray, held: np.ndarray,
                  subject: str | None = None) -> np.ndarray:
    """tau [T] under the gap rule (``base.timebase.grid_segments``): the larynx model run on each run of frames
    from its initial state, the points inside a gap holding the tau before them."""
    tau = np.zeros(len(psi))
    for s in np.unique(segment):
        points = (segment == s) & ~held
        if points.any():
            tau[points] = predict_tau(model, psi[points], subject)
    return fill_held(tau, held)


@torch.no_grad()
def head_theta(cfg: InferConfig, models: Models, track: ExpressionTrack,
               announce=print) -> tuple[torch.Tensor, torch.Tensor]:
    """Bone-frame theta [T,J,3] from the take's head rotation, and the head orientation it poses [T,3,3]
    (``HeadNeckModel.head_rotation``: the target where the joint limits let the chain reach it); the neck at
    rest (zeros, the identity) without a neck model or a rotation."""
    rest = (torch.zeros(len(track), models.rig.num_joints, 3), torch.eye(3).repeat(len(track), 1, 1))
    if models.neck is None:
        return rest
    if track.head_rotation is not None:  # a face video's pose: rotation matrices in the rig's frame
        signs = (float(cfg.yaw_sign), float(cfg.pitch_sign), float(cfg.roll_sign))
        if signs != (1.0, 1.0, 1.0):
            raise InputError(f"{track.source}: yaw_sign/pitch_sign/roll_sign={signs} apply to recorded yaw, pitch "
                             f"and roll; a video's head pose is already in the rig's frame (mirror=true for "
                             f"selfie-mirrored footage)")
        head = torch.as_tensor(track.head_rotation, dtype=torch.float32)
    elif track.head_ypr is None:
        announce(f"{track.source}: no head rotation recorded (HeadYaw/HeadPitch/HeadRoll absent or zero); "
                 f"the neck rests")
        return rest
    else:
        signs = (float(cfg.yaw_sign), float(cfg.pitch_sign), float(cfg.roll_sign))
        head = head_rotations_from_ypr(track.head_ypr, cfg.head_units, signs,
                                       f"{track.source} (HeadYaw, HeadPitch, HeadRoll)")
    theta = predict_theta(models.neck, models.rig, recentered(head) if cfg.recenter else head)
    return theta, models.rig.head_rotation(theta)


def animate(cfg: InferConfig, models: Models, track: ExpressionTrack, announce=print,
            audio: str | None = None, seconds: StageSeconds | None = None) -> AnimationParams:
    """The per-frame rig inputs for one take; the seconds each stage took are added to ``seconds``.

    With ``audio`` (the take's sound, aligned with the capture at their start) the voice term
    (``motion.voice``: larynx height from F0, zero-mean over the take) is added to the larynx model's tau,
    before swallows are inserted; without it nothing changes."""
    seconds = StageSeconds() if seconds is None else seconds
    with seconds.time("resample"):
        fps = models.larynx.fps if models.larynx is not None else float(cfg.out_fps or track.fps)
        uniform = track.resampled(fps, GAP_SECONDS)  # the gap rule, as the live receiver applies it
    with seconds.time("larynx"):
        if models.larynx is not None:
            tau = segmented_tau(models.larynx, uniform.psi, *grid_segments(track.time, fps), cfg.subject)
        else:
            tau = np.zeros(len(uniform))
    f0 = tau_voice = None
    voice_producers = {}
    if audio is not None:
        with seconds.time("voice"):
            frame_time = uniform.time - uniform.time[0]
            capture_seconds = float(track.time[-1] - track.time[0]) + 1.0 / track.fps
            f0, tau_voice, summary = voice_on_frames(audio, frame_time, str(track.source), capture_seconds,
                                                     load_voice(cfg.voice), cfg.audio_tolerance, announce)
            if tau_voice is not None:
                tau = tau + tau_voice
            voice_producers = {"audio": str(audio), "voice": str(cfg.voice), **summary}
    onsets = [float(t) for t in as_list(cfg.swallow_at)]
    if track.source == DEMO_SOURCE and not onsets:
        onsets = [SWALLOW_ONSET]
    if onsets:
        path = pretrained_path("swallow_template") if cfg.swallow_template == "default" else cfg.swallow_template
        template = read_template(path)
        playback = cfg.swallow_playback
        try:
            tau = insert_swallows(tau, uniform.time, template, onsets, as_list(cfg.swallow_duration_scale),
                                  as_list(cfg.swallow_amplitude_scale), playback)
        except ValueError as e:  # an onset outside the take, scales that do not match the onsets
            raise InputError(f"swallow_at={onsets} in {track.source}: {e}") from None
    with seconds.time("head2neck"):
        theta, head = head_theta(cfg, models, uniform, announce)
    return AnimationParams(
        time=uniform.time - uniform.time[0], fps=fps, psi=uniform.psi, tau=tau,
        eta=np.full(len(uniform), float(cfg.eta)), theta=theta.numpy(), head_rotation=head.numpy(),
        joint_names=models.rig.joint_names, expression_names=models.rig.expression_names,
        rig=models.rig_name, rig_checksum=rig_checksum(models.rig.rig),
        producers={**models.producers, "swallows": onsets, "source": str(track.source), **voice_producers},
        f0=f0, tau_voice=tau_voice)
