"""The larynx tracker's inputs (motion/track/): normal-map folders (PNG, TIFF, EXR), .npy stacks and videos
decoded as written, and bad input refused naming the file and what was expected."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from base.cli import compose_config
from base.errors import InputError
from base.files import save_npy
from base.tables import CsvTable
from data.normals import encode_normals, write_normal_image
from motion.track import (
    check_normal_map,
    decode_frame,
    kernel_from_file,
    open_source,
    run,
)
from scene.normal_sequences import SequenceConfig, make_sequence, write_sequence


def track_cli(overrides: list[str]) -> dict:
    return run(compose_config("track", overrides))


def read_all(path, **kwargs) -> np.ndarray:
    return np.stack([n for _, _, n in open_source(path, **kwargs).frames()])


@pytest.mark.parametrize("image_format,tolerance", [("png8", 2.1 / 255), ("png16", 3e-5), ("exr", 1e-6)])
def test_folder_readers_decode_what_was_written(tmp_path, short, image_format, tolerance):
    write_sequence(tmp_path, short, image_format)
    source = open_source(tmp_path)
    assert source.kind == "folder" and source.count == 12 and source.fps == 30.0
    frames = read_all(tmp_path)
    assert frames.shape == short.normals.shape
    assert float(np.abs(frames - short.normals).max()) <= tolerance
    assert np.array_equal(np.abs(frames).sum(-1) > 0, short.mask)        # background decoded as 0
    assert open_source(tmp_path, fps=50.0).fps == 50.0


@pytest.mark.parametrize("bits,tolerance", [(8, 2.1 / 255), (16, 3e-5)])
def test_tiff_folders(tmp_path, short, bits, tolerance):
    for t, frame in enumerate(short.normals):
        write_normal_image(tmp_path / f"f{t}.tif", frame, bits)
    frames = read_all(tmp_path)
    # Sorted with numbers as numbers: f2 before f10.
    assert [p.name for p in open_source(tmp_path).files][:3] == ["f0.tif", "f1.tif", "f2.tif"]
    assert float(np.abs(frames - short.normals).max()) <= tolerance


@pytest.mark.parametrize("dtype", ["raw", "encoded", "uint8", "uint16"])
def test_npy_stacks_in_each_encoding(tmp_path, short, dtype):
    stack = {"raw": short.normals, "encoded": encode_normals(short.normals),
             "uint8": np.rint(encode_normals(short.normals) * 255).astype(np.uint8),
             "uint16": np.rint(encode_normals(short.normals) * 65535).astype(np.uint16)}[dtype]
    save_npy(tmp_path / "s.npy", stack)
    frames = read_all(tmp_path / "s.npy")
    tolerance = {"raw": 1e-6, "encoded": 1e-6, "uint8": 2.1 / 255, "uint16": 3e-5}[dtype]
    assert float(np.abs(frames - short.normals).max()) <= tolerance


def write_video(path: Path, frames: np.ndarray, fps: float) -> bool:
    """Frames [T,H,W,3] as a video; True when lossless (FFV1)."""
    size = frames.shape[2], frames.shape[1]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"FFV1"), fps, size)
    lossless = writer.isOpened()
    if not lossless:  # pragma: no cover - builds without FFV1
        writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, size)
    for n in frames:
        writer.write(np.rint(encode_normals(n)[..., ::-1] * 255).astype(np.uint8))
    writer.release()
    return lossless


def test_video_reader(tmp_path, short):
    path = tmp_path / "clip.avi"
    lossless = write_video(path, short.normals, 25.0)
    source = open_source(path)
    assert source.kind == "video" and source.fps == pytest.approx(25.0)
    frames = read_all(path)
    assert frames.shape == short.normals.shape
    tolerance = 2.1 / 255 if lossless else 0.15
    interior = short.mask & np.roll(short.mask, 2, 1) & np.roll(short.mask, -2, 1)
    assert float(np.abs(frames - short.normals)[interior].mean()) <= tolerance


def test_video_tracked_end_to_end(tmp_path, builtin_rig):
    """A video through the command line: its own frame rate in the time column, the larynx found."""
    seq = make_sequence(builtin_rig, SequenceConfig(frames=30, size=160, cm_per_px=0.1, noise=0.02,
                                                    head_motion_deg=2.0, swallows_per_minute=60.0), seed=7)
    write_video(tmp_path / "neck.avi", seq.normals, 24.0)
    out = tmp_path / "track.csv"
    track_cli([f"input={tmp_path / 'neck.avi'}", f"out={out}", "plot=null", "progress=false", "cm_per_px=0.1"])
    table = CsvTable(out)
    assert len(table) == 30
    np.testing.assert_allclose(table.numeric("time"), np.arange(30) / 24.0, atol=1e-6)
    err = np.hypot(table.numeric("x_px") - seq.larynx_px[:, 0], table.numeric("y_px") - seq.larynx_px[:, 1])
    assert np.median(err) < 0.6


def test_video_errors(tmp_path, short, monkeypatch):
    (tmp_path / "broken.mp4").write_bytes(b"\x00" * 512)
    with pytest.raises(InputError, match=r"broken\.mp4: OpenCV cannot open this video"):
        open_source(tmp_path / "broken.mp4")
    write_video(tmp_path / "clip.avi", short.normals[:3], 25.0)
    # A container without a frame rate (as some screen recorders write): OpenCV reports 0.
    real_get = cv2.VideoCapture.get
    monkeypatch.setattr(cv2.VideoCapture, "get",
                        lambda self, prop: 0.0 if prop == cv2.CAP_PROP_FPS else real_get(self, prop))
    with pytest.raises(InputError, match=r"clip\.avi: the video reports no frame rate; give fps="):
        open_source(tmp_path / "clip.avi")
    assert open_source(tmp_path / "clip.avi", fps=12.5).fps == 12.5


def test_non_normal_images_are_refused_naming_the_file(tmp_path, short):
    write_sequence(tmp_path, short, "png8")
    rows, cols = np.mgrid[0:128, 0:128]
    photo = np.stack([np.full_like(rows, 200), 255 * rows // 127, 255 * cols // 127], -1).astype(np.uint8)
    cv2.imwrite(str(tmp_path / "frame_00005.png"), photo)       # a colourful non-normal image mid-sequence
    with pytest.raises(InputError, match=r"frame_00005\.png: not a normal map"):
        read_all(tmp_path)
    with pytest.raises(InputError, match="background"):
        check_normal_map(decode_frame(np.full((64, 64, 3), 0.5, np.float32), False), "grey.png")


def test_input_errors_name_what_was_expected(tmp_path, short):
    with pytest.raises(InputError, match="not found"):
        open_source(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no normal-map images"):
        open_source(tmp_path / "empty")
    save_npy(tmp_path / "flat.npy", np.zeros((4, 8, 8)))
    with pytest.raises(InputError, match=r"expected a normal-map stack \[T,H,W,3\]"):
        open_source(tmp_path / "flat.npy")
    (tmp_path / "x.txt").write_text("hi")
    with pytest.raises(InputError, match="unsupported input"):
        open_source(tmp_path / "x.txt")
    folder = tmp_path / "mixed"
    write_sequence(folder, short, "png8")
    write_normal_image(folder / "frame_00003.png", short.normals[3][:64])
    with pytest.raises(InputError, match=r"frame_00003\.png: frame of size 128x64, expected 128x128"):
        read_all(folder)
    save_npy(tmp_path / "k.npy", np.zeros((70, 70, 2), np.float32))
    with pytest.raises(InputError, match=r"expected a kernel \[h,w,3\]"):
        kernel_from_file(tmp_path / "k.npy")
