"""The files of a live session: per phone ``params.npz`` (``data.params``, as infer.py writes it) and
``capture.csv`` (a Live Link Face CSV that infer.py reads back), and the session's ``summary.json``.
"""
from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import torch

from base.files import write_text
from data.params import AnimationParams, rig_checksum, save_params
from motion.live.packet import VALUE_COUNT, VALUE_NAMES
from motion.live.stream import PhoneStream, timecode


def folder_names(streams: list[PhoneStream]) -> dict[tuple[str, str], str]:
    """One folder name per stream: the subject, with the device id added when two phones share a subject;
    anything but letters, digits, ``-_.`` becomes ``_`` (a subject is never a path)."""
    def clean(text: str) -> str:
        return re.sub(r"[^A-Za-z0-9_.-]", "_", text).strip(".") or "subject"

    counts: dict[str, int] = {}
    for stream in streams:
        counts[stream.subject] = counts.get(stream.subject, 0) + 1
    return {s.key: clean(s.subject if counts[s.subject] == 1 else f"{s.subject}-{s.device}") for s in streams}


def capture_text(stream: PhoneStream) -> str:
    """The accepted frames as a Live Link Face CSV (``Timecode,BlendShapeCount,<61 values>``), the gaps by
    frame number filled by linear interpolation (the reader's own, so a re-read gives the same track).
    Values are written with 9 significant digits: a float32 reads back exactly."""
    record, rate = stream.recorded, stream.timecode_rate
    frames = np.asarray(record.frames, dtype=np.int64)
    values = np.stack(record.values).astype(np.float64)
    subframes = np.asarray(record.subframes, dtype=np.float64)
    every = np.arange(frames[0], frames[-1] + 1)
    filled = np.stack([np.interp(every, frames, values[:, k]) for k in range(VALUE_COUNT)], axis=1)
    received = dict(zip(frames.tolist(), range(len(frames))))
    lines = ["Timecode,BlendShapeCount," + ",".join(VALUE_NAMES)]
    for n, row in zip(every.tolist(), filled):
        k = received.get(n)
        code = timecode(n, subframes[k] if k is not None else 0.0, rate)
        cells = values[k] if k is not None else row.astype(np.float32)
        lines.append(f"{code},{VALUE_COUNT}," + ",".join(f"{float(v):.9g}" for v in cells))
    return "\n".join(lines) + "\n"


def stream_params(stream: PhoneStream, eta: float) -> AnimationParams:
    """The output frames of a stream as ``AnimationParams`` (head_rotation from theta, as infer.py does)."""
    models, record = stream.models, stream.recorded
    theta = np.stack(record.theta).astype(np.float32)
    with torch.no_grad():
        head = models.rig.head_rotation(torch.as_tensor(theta)).numpy()
    count = len(record.tau)
    producers = {**models.producers, "tool": "motion.live", "swallows": [],
                 "source": f"live: device {stream.device}, subject {stream.subject}",
                 "head_units": stream.options.head_units, "signs": list(stream.options.signs),
                 "recenter": stream.options.recenter}
    return AnimationParams(
        time=np.arange(count) / stream.fps, fps=stream.fps, psi=np.stack(record.psi), tau=np.asarray(record.tau),
        eta=np.full(count, float(eta)), theta=theta, head_rotation=head,
        joint_names=models.rig.joint_names, expression_names=models.rig.expression_names,
        rig=models.rig_name, rig_checksum=rig_checksum(models.rig.rig), producers=producers)


def stream_summary(stream: PhoneStream) -> dict:
    return {"device": stream.device, "subject": stream.subject, "fps_in": stream.fps_in, "fps": stream.fps,
            "frames": len(stream.recorded.frames), "output_frames": len(stream.recorded.tau),
            "missing_frames": stream.missing, "late_frames": stream.late, "clamped_values": stream.clamped,
            "latency_ms": stream.latency()}


def write_session(staging: Path, streams: list[PhoneStream], rejected: dict, eta: float,
                  extra: dict | None = None) -> dict:
    """Write every stream's folder and ``summary.json`` into ``staging``; returns the summary."""
    names = folder_names(streams)
    subjects = {}
    for stream in streams:
        if not stream.recorded.frames:
            continue
        folder = staging / names[stream.key]
        folder.mkdir(parents=True, exist_ok=True)
        write_text(folder / "capture.csv", capture_text(stream))
        if stream.recorded.tau:
            save_params(folder / "params.npz", stream_params(stream, eta))
        subjects[names[stream.key]] = stream_summary(stream)
    summary = {"rejected": dict(sorted(rejected.items())), "subjects": subjects, **(extra or {})}
    write_text(staging / "summary.json", json.dumps(summary, indent=2) + "\n")
    return summary
