"""The files of a live session, written as it goes (:class:`SessionWriter`): per phone ``capture.csv`` (a Live
Link Face CSV that infer.py reads back), appended and flushed straight into ``out_dir/<subject>/`` after every
drain of the socket, so a crash or SIGKILL keeps what was received; ``params.npz`` (``data.params``, as
infer.py writes it) when the stream closes (stop, idle, error); the session's ``summary.json`` at stop.  Each
of the last two is written whole (temporary file, then rename: ``base.files``).

Names are made safe here: :func:`printable` for the log (control characters escaped, length bounded) and
:class:`FolderNames` for the folders (a subject is never a path; two subjects that clean to the same name, or
differ only in case, get distinct folders).
"""
from __future__ import annotations

import json
import os
import re
from pathlib import Path

import numpy as np
import torch

from base.files import write_text
from data.params import AnimationParams, rig_checksum, save_params
from motion.live.packet import VALUE_NAMES
from motion.live.stream import PhoneStream

CAPTURE_HEADER = "Timecode,BlendShapeCount," + ",".join(VALUE_NAMES) + "\n"
SUMMARY = "summary.json"
NAME_CHARS = 48  # of a folder name made from a subject (and device id)
# Windows' reserved device names (a folder named so cannot be opened there) and the session's own file
_RESERVED = {"con", "prn", "aux", "nul", *(f"com{k}" for k in range(1, 10)), *(f"lpt{k}" for k in range(1, 10)),
             SUMMARY}


def printable(text: str, limit: int = 80) -> str:
    """``text`` safe to print: control and other non-printable characters escaped (``\\x1b``, ``\\u202e``),
    at most ``limit`` characters kept (then ``...``)."""
    out = "".join(c if c.isprintable() else c.encode("unicode_escape").decode("ascii") for c in text[:limit])
    return out + ("..." if len(text) > limit else "")


def clean(text: str) -> str:
    """A folder name from ``text``: anything but letters, digits, ``-_.`` becomes ``_``, no leading dot,
    at most :data:`NAME_CHARS` characters."""
    return re.sub(r"[^A-Za-z0-9_.-]", "_", text)[:NAME_CHARS].strip(".") or "subject"


class FolderNames:
    """One distinct folder name per stream of a session, in the order they start: the subject; the subject and
    device id when that is taken (two phones, one subject); then ``-2``, ``-3``, ... (a phone back after its
    stream expired, ``a/b`` after ``a_b``).  Compared case-blind (macOS and Windows folders are)."""

    def __init__(self):
        self.used: set[str] = set()

    def take(self, subject: str, device: str) -> str:
        first, second = clean(subject), clean(f"{subject}-{device}")
        candidates = [first, second] + [f"{first}-{k}" for k in range(2, len(self.used) + 3)]
        name = next(c for c in candidates if c.lower() not in self.used and c.lower() not in _RESERVED)
        self.used.add(name.lower())
        return name


def capture_text(stream: PhoneStream) -> str:
    """The stream's capture.csv lines not yet written (taken from it)."""
    text = "".join(stream.rows)
    stream.rows.clear()
    return text


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
    return {"device": stream.device, "subject": stream.subject, "address": list(stream.address or ()),
            "fps_in": stream.fps_in, "timecode_fps": stream.timecode_rate, "fps": stream.fps,
            "frames": stream.recorded.frames, "output_frames": len(stream.recorded.tau),
            "held_frames": stream.recorded.held, "gaps": stream.gaps, "missing_frames": stream.missing,
            "late_frames": stream.late, "clamped_values": stream.clamped, "latency_ms": stream.latency(),
            "closed": stream.closed}


class SessionWriter:
    """A live session's folder ``out_dir`` (made by the caller, new): :meth:`open` a stream's folder and
    capture.csv, :meth:`append` its new rows (one write, then on disk), :meth:`close` it (its params.npz),
    :meth:`finish` (summary.json)."""

    def __init__(self, out_dir: Path, eta: float):
        self.out_dir, self.eta = Path(out_dir), eta
        self.names = FolderNames()
        self.files: dict[int, int] = {}  # id(stream) -> file descriptor of its capture.csv
        self.subjects: dict[str, dict] = {}

    def open(self, stream: PhoneStream) -> None:
        stream.folder = self.names.take(stream.subject, stream.device)
        folder = self.out_dir / stream.folder
        folder.mkdir(parents=True, exist_ok=False)
        fd = os.open(folder / "capture.csv", os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_APPEND, 0o666)
        self.files[id(stream)] = fd
        self._write(fd, CAPTURE_HEADER)

    @staticmethod
    def _write(fd: int, text: str) -> None:
        data = text.encode("utf-8")
        while data:  # one write in practice (a regular file); a short write goes on where it stopped
            data = data[os.write(fd, data):]

    def append(self, stream: PhoneStream) -> None:
        """The stream's new capture.csv rows onto the disk (OSError: the caller closes the stream)."""
        if stream.rows:
            self._write(self.files[id(stream)], capture_text(stream))

    def close(self, stream: PhoneStream, reason: str) -> dict:
        """Close a stream: its last rows, its params.npz (whole), its summary entry; the entry.  Whatever
        fails is named in the entry (``error``), and the stream's memory is let go."""
        stream.closed = stream.closed or reason
        entry = stream_summary(stream)
        fd = self.files.pop(id(stream), None)
        try:
            if fd is not None:
                try:
                    self._write(fd, capture_text(stream))
                finally:
                    os.close(fd)
            if stream.recorded.tau and stream.folder is not None:
                save_params(self.out_dir / stream.folder / "params.npz", stream_params(stream, self.eta))
        except Exception as e:  # noqa: BLE001 -- one stream's files must not stop the others'
            entry["error"] = f"{type(e).__name__}: {e}"
        stream.recorded.psi, stream.recorded.tau, stream.recorded.theta = [], [], []
        self.subjects[stream.folder or f"unwritten-{len(self.subjects)}"] = entry
        return entry

    def finish(self, rejected: dict, extra: dict | None = None) -> dict:
        """summary.json (written whole): ``rejected`` by reason, each closed stream's entry by folder."""
        summary = {"rejected": dict(sorted(rejected.items())), "subjects": self.subjects, **(extra or {})}
        write_text(self.out_dir / SUMMARY, json.dumps(summary, indent=2) + "\n")
        return summary


def write_session(staging: Path, streams: list[PhoneStream], rejected: dict, eta: float,
                  extra: dict | None = None) -> dict:
    """Every stream's folder and ``summary.json`` into ``staging`` at once (the face feed, whose streams kept
    their rows); returns the summary."""
    writer = SessionWriter(staging, eta)
    for stream in streams:
        if stream.recorded.frames:
            writer.open(stream)
            writer.close(stream, stream.closed or "stop")
    return writer.finish(rejected, extra)
