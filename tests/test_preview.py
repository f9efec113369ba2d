"""Preview video (scene.preview): frames that follow the pose, the strip, side by side, the mp4 file."""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np
import pytest
import torch

from base.cli import run_cli
from base.errors import InputError
from data.params import AnimationParams, rig_checksum, save_params
from scene.preview import Panel, output_frames, preview_image, run, view_rotation, write_preview


def nod_clip(rig, frames: int = 10, fps: float = 30.0, flexion: float = 0.1) -> AnimationParams:
    """Rest at frame 0, then a forward nod growing to ``flexion`` rad at every joint (anatomical x); tau
    rising from 0 to 0.03."""
    anatomical = np.zeros((frames, rig.num_joints, 3))
    anatomical[..., 0] = np.linspace(0.0, flexion, frames)[:, None]
    theta = rig.from_anatomical(torch.tensor(anatomical, dtype=torch.float32))
    with torch.no_grad():
        head = rig.head_rotation(theta)
    return AnimationParams(time=np.arange(frames) / fps, fps=fps, psi=np.zeros((frames, 55)),
                           tau=np.linspace(0, 0.03, frames), eta=np.ones(frames), theta=theta.numpy(),
                           head_rotation=head.numpy(), joint_names=rig.joint_names,
                           expression_names=rig.expression_names, rig_checksum=rig_checksum(rig.rig))


def mask_of(image: np.ndarray, size: int) -> np.ndarray:
    """Covered pixels of the render part of a preview frame (anything but the background colour)."""
    render = image[:size].astype(int)
    return np.abs(render - np.array([38, 34, 30])).sum(-1) > 6


def test_views_are_rotations_about_the_vertical():
    for view, towards in (("front", [0, 0, 1]), ("side", [1, 0, 0])):
        rotation = view_rotation(view)
        np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(rotation) == pytest.approx(1.0)
        np.testing.assert_allclose(rotation[2], towards, atol=1e-12)   # camera z: towards the camera
        np.testing.assert_allclose(rotation[1], [0, 1, 0], atol=1e-12)  # up stays up
    with pytest.raises(InputError, match="view=top"):
        view_rotation("top")


def test_the_render_follows_the_nod(builtin_rig):
    """The silhouette's bounding box is that of the posed mesh projected through the camera, at rest and
    nodded; seen from the subject's left (image left = forward) the nod moves the front edge left."""
    size = 96
    params = nod_clip(builtin_rig, flexion=0.1)
    panel = Panel.create(builtin_rig, params, size=size, view="side", strip=False)
    images = panel.frames(np.array([0, len(params) - 1]))
    with torch.no_grad():
        posed = builtin_rig(torch.as_tensor(params.theta[[0, -1]]))
    boxes = []
    for image, vertices in zip(images, posed):
        pixels, _ = panel.camera.project(vertices)
        rows, cols = np.nonzero(mask_of(image, size))
        expected = [float(pixels[:, 0].min()), float(pixels[:, 1].min()), float(pixels[:, 0].max()),
                    float(pixels[:, 1].max())]
        np.testing.assert_allclose([cols.min(), rows.min(), cols.max(), rows.max()], expected, atol=1.5)
        assert cols.min() >= 0 and cols.max() <= size - 1 and rows.min() >= 0   # framed: nothing cut off
        boxes.append(expected)
    assert boxes[0][0] - boxes[1][0] > 5


def test_shading_modes(builtin_rig):
    params = nod_clip(builtin_rig, frames=2)
    normals = Panel.create(builtin_rig, params, size=64, shading="normals", strip=False).frames(np.array([0]))[0]
    shaded = Panel.create(builtin_rig, params, size=64, strip=False).frames(np.array([0]))[0]
    mask = mask_of(shaded, 64)
    assert 0.15 < mask.mean() < 0.9
    # Normal-map colours decode to unit normals facing the camera (front view: n_z > 0).
    n = normals[mask][:, ::-1] / 255.0 * 2.0 - 1.0
    assert np.median(np.linalg.norm(n, axis=1)) == pytest.approx(1.0, abs=0.03)
    assert (n[:, 2] > -0.05).mean() > 0.98
    with pytest.raises(InputError, match="shading=flat"):
        Panel.create(builtin_rig, params, size=64, shading="flat")


def test_strip_cursor_and_values(builtin_rig):
    params = nod_clip(builtin_rig, frames=10)
    panel = Panel.create(builtin_rig, params, size=128)
    strip = panel.strip
    white = [np.flatnonzero((strip.draw(i)[:, : strip.plot_width] == 255).all(-1).sum(0) > strip.base.shape[0] // 2)
             for i in (0, 9)]
    assert list(white[0]) == [0] and list(white[1]) == [strip.plot_width - 1]
    # the summed flexion of the last frame: 8 joints x 0.1 rad
    assert strip.angles[9, :, 0].sum() == pytest.approx(np.degrees(0.8), rel=1e-3)
    frame = panel.frames(np.array([3]))[0]
    assert frame.shape == (128 + strip.base.shape[0], 128, 3)


def test_side_by_side(builtin_rig, turned_rig):
    """Two characters: each column is that character's own single-panel frame."""
    first = nod_clip(builtin_rig, frames=4)
    second = dataclasses.replace(first, theta=turned_rig.from_anatomical(builtin_rig.to_anatomical(
        torch.as_tensor(first.theta))).numpy(), rig_checksum=rig_checksum(turned_rig.rig))
    left = Panel.create(builtin_rig, first, size=64)
    right = Panel.create(turned_rig, second, size=64)
    image = preview_image([left, right], 2)
    assert image.shape[1] == 128
    np.testing.assert_array_equal(image[:, :64], preview_image([left], 2))
    np.testing.assert_array_equal(image[:, 64:], preview_image([right], 2))
    short = Panel.create(builtin_rig, nod_clip(builtin_rig, frames=3), size=64)
    with pytest.raises(InputError, match="different lengths"):
        write_preview("unused.mp4", [left, short])


def test_video_file(builtin_rig, tmp_path):
    params = nod_clip(builtin_rig, frames=12)
    panel = Panel.create(builtin_rig, params, size=64)
    report = write_preview(tmp_path / "p.mp4", [panel])
    capture = cv2.VideoCapture(str(tmp_path / "p.mp4"))
    frames = []
    while True:
        ok, image = capture.read()
        if not ok:
            break
        frames.append(image)
    assert len(frames) == report.frames == 12
    assert frames[0].shape == (64 + panel.strip.base.shape[0], 64, 3)
    assert capture.get(cv2.CAP_PROP_FPS) == pytest.approx(30.0)
    # the decoded frame is the rendered one up to compression
    assert np.abs(frames[5].astype(int) - preview_image([panel], 5).astype(int)).mean() < 12
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.mp4"]     # no temporary left
    with pytest.raises(InputError, match="expected an .mp4"):
        write_preview(tmp_path / "p.avi", [panel])


def test_output_rate():
    params = AnimationParams(time=np.arange(31) / 30.0, fps=30.0, psi=np.zeros((31, 55)), tau=np.zeros(31),
                             eta=np.ones(31), theta=np.zeros((31, 8, 3)), head_rotation=np.tile(np.eye(3), (31, 1, 1)),
                             joint_names=[str(i) for i in range(8)], expression_names=[str(i) for i in range(55)])
    frames, fps = output_frames(params, 15.0)
    assert fps == 15.0 and list(frames) == list(range(0, 31, 2))
    frames, fps = output_frames(params, None)
    assert fps == 30.0 and list(frames) == list(range(31))
    with pytest.raises(InputError, match="fps=0"):
        output_frames(params, 0.0)


def test_command_line(builtin_rig, tmp_path, capsys):
    source = tmp_path / "params.npz"
    save_params(source, nod_clip(builtin_rig, frames=6))
    run_cli("preview", run, [f"source={source}", f"out={tmp_path / 'v.mp4'}", "size=64", "view=three_quarter",
                             f"still={tmp_path / 's.png'}", "still_frame=5"])
    assert "6 frames" in capsys.readouterr().out
    still = cv2.imread(str(tmp_path / "s.png"))
    assert still.shape[:2] == (64 + 2 * int(round(64 * 0.34 / 2)), 64)
    for argv, message in (["view=top"], "view=top"), (["size=63"], "size=63"), (["still_frame=9", "still=x.png"],
                                                                                   "still_frame=9"):
        with pytest.raises(SystemExit) as exit_:
            run_cli("preview", run, [f"source={source}", f"out={tmp_path / 'w.mp4'}", "size=64", *argv])
        assert exit_.value.code == 2
        assert message in capsys.readouterr().err
