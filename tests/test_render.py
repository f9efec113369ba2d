"""Normal-map renderer (data/render.py) and synthetic sequences (data/normal_sequences.py).

The renderer is checked against analytic surfaces (a plane, a sphere), its projection against its own
rasterised depth, and the encoding against its definition (n + 1) / 2 on disk.
"""
from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from data.errors import InputError
from data.normal_sequences import SequenceConfig, head_motion, make_sequence, write_sequence
from data.normals import encode_normals, read_normal_image, stored_to_unit, write_normal_image
from data.render import Camera, NeckRenderer, larynx_areas, larynx_point, neck_camera, outward_faces, render_normals, rest_larynx_point


def grid_plane(size_cm: float, z: float, cells: int = 8) -> tuple[torch.Tensor, torch.Tensor]:
    """A square [-size/2, size/2]^2 at depth z facing +z: vertices [1,N,3], triangles [F,3] counter-clockwise."""
    lin = torch.linspace(-size_cm / 2, size_cm / 2, cells + 1)
    yy, xx = torch.meshgrid(lin, lin, indexing="ij")
    vertices = torch.stack([xx, yy, torch.full_like(xx, z)], -1).reshape(1, -1, 3)
    idx = torch.arange((cells + 1) ** 2).reshape(cells + 1, cells + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]   # (x, y): a lower-left, c upper-right
    faces = torch.cat([torch.stack([a, b, c], -1).reshape(-1, 3), torch.stack([a, c, d], -1).reshape(-1, 3)])
    return vertices, faces


def uv_sphere(radius: float, centre, rows: int = 64, cols: int = 128) -> tuple[torch.Tensor, torch.Tensor]:
    theta = torch.linspace(0, np.pi, rows + 1)[1:-1]
    phi = torch.linspace(0, 2 * np.pi, cols + 1)[:-1]
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    ring = torch.stack([torch.sin(t) * torch.cos(p), torch.cos(t), torch.sin(t) * torch.sin(p)], -1).reshape(-1, 3)
    points = torch.cat([torch.tensor([[0.0, 1.0, 0.0]]), ring, torch.tensor([[0.0, -1.0, 0.0]])])
    vertices = (radius * points + torch.tensor(centre)).reshape(1, -1, 3)
    idx = torch.arange(len(ring)).reshape(rows - 1, cols) + 1
    nxt = torch.roll(idx, -1, dims=1)
    faces = [torch.stack([idx[:-1], idx[1:], nxt[1:]], -1).reshape(-1, 3),
             torch.stack([idx[:-1], nxt[1:], nxt[:-1]], -1).reshape(-1, 3),
             torch.stack([torch.zeros(cols, dtype=torch.long), idx[0], nxt[0]], -1),
             torch.stack([torch.full((cols,), len(points) - 1), nxt[-1], idx[-1]], -1)]
    faces = torch.cat(faces)
    return vertices, outward_faces(vertices[0], faces.numpy())


@pytest.mark.parametrize("perspective", [False, True])
def test_plane_facing_the_camera_renders_normal_001_over_its_projected_area(perspective):
    vertices, faces = grid_plane(4.0, z=0.0)
    camera = Camera(centre=(0.0, 0.0, 0.0), width=96, height=80, cm_per_px=0.1, perspective=perspective)
    render = render_normals(vertices, faces, camera)
    normals = render.normals[0][render.mask[0]]
    assert torch.allclose(normals, torch.tensor([0.0, 0.0, 1.0]).expand_as(normals), atol=1e-5)
    # 4 cm at 0.1 cm/px (at the centre's depth, perspective too): a 40 px square, 1600 +- its border.
    assert abs(int(render.mask[0].sum()) - 1600) <= 4 * 41
    assert torch.allclose(render.depth[0][render.mask[0]], torch.tensor(camera.distance), atol=1e-3)
    # Seen from behind (winding reversed), the plane is culled.
    assert not render_normals(vertices, faces[:, [0, 2, 1]], camera).mask.any()


@pytest.mark.parametrize("perspective", [False, True])
def test_sphere_normals_match_the_analytic_normals(perspective):
    radius, centre = 3.0, (0.4, -0.3, 0.0)
    vertices, faces = uv_sphere(radius, centre)
    camera = Camera(centre=(0.0, 0.0, 0.0), width=96, height=96, cm_per_px=0.08, perspective=perspective,
                    distance=30.0)
    render = render_normals(vertices, faces, camera)
    mask = render.mask[0]
    # Analytic: the visible intersection of each pixel's ray with the sphere; here via the rendered depth.
    rows, cols = torch.nonzero(mask, as_tuple=True)
    depth = render.depth[0][mask]
    cx, cy = camera.principal_point
    scale = depth / camera.focal_px if perspective else torch.full_like(depth, camera.cm_per_px)
    points = torch.stack([(cols - cx) * scale, (cy - rows) * scale, camera.distance - depth], -1)
    analytic = (points - torch.tensor(centre)) / radius
    analytic = analytic / analytic.norm(dim=-1, keepdim=True)
    angle = torch.rad2deg(torch.arccos((render.normals[0][mask] * analytic).sum(-1).clamp(-1, 1)))
    interior = render.normals[0][mask][:, 2] > 0.3            # away from the silhouette
    assert float(angle[interior].median()) < 0.5
    assert float(angle[interior].max()) < 2.0
    # Silhouette radius: the sphere covers pi r^2 / s^2 pixels (orthographic; perspective slightly more).
    expected = np.pi * (radius / camera.cm_per_px) ** 2
    assert expected * 0.97 < int(mask.sum()) < expected * (1.12 if perspective else 1.03)


@pytest.mark.parametrize("perspective", [False, True])
def test_projected_vertices_land_where_they_render(perspective):
    vertices, faces = uv_sphere(2.5, (0.0, 0.0, 1.0), rows=24, cols=48)
    camera = Camera(centre=(0.0, 0.0, 0.0), width=80, height=80, cm_per_px=0.1, perspective=perspective)
    render = render_normals(vertices, faces, camera)
    pixels, depth = camera.project(vertices[0])
    facing = ((vertices[0] - torch.tensor([0.0, 0.0, 1.0])) / 2.5)[:, 2] > 0.7
    cols, rows = pixels[facing].round().long().unbind(-1)
    assert bool(render.mask[0, rows, cols].all())
    # Within half a pixel the surface depth changes by at most ~0.7 px * cm_per_px where n_z > 0.7.
    assert float((render.depth[0, rows, cols] - depth[facing]).abs().max()) < 0.1
    assert pixels.shape == (vertices.shape[1], 2)


def test_batched_render_equals_single_frames(builtin_rig):
    renderer = NeckRenderer(builtin_rig, neck_camera(builtin_rig, 64, 0.3))
    theta = torch.tensor(head_motion(5, 10.0, seed=0, amplitude_deg=8.0, max_hz=1.0), dtype=torch.float32)
    tau = torch.linspace(-0.02, 0.05, 5)
    batch = renderer(theta, tau=tau, chunk=2)
    for i in range(5):
        single = renderer(theta[i:i + 1], tau=tau[i:i + 1])
        assert torch.equal(single.mask[0], batch.mask[i])
        assert torch.allclose(single.normals[0], batch.normals[i], atol=1e-5)


def test_neck_view_is_centred_on_the_larynx_and_the_larynx_faces_the_camera(builtin_rig):
    camera = neck_camera(builtin_rig, 128, 0.1)
    renderer = NeckRenderer(builtin_rig, camera)
    render, pixels = renderer.render_with_truth(builtin_rig.neutral(1))
    assert torch.allclose(pixels[0], torch.tensor([63.5, 63.5]), atol=1e-3)
    assert bool(render.mask[0, 54:74, 54:74].all())
    assert float(render.normals[0, 54:74, 54:74, 2].min()) > 0.3      # the front of the neck faces +z
    # Rest larynx point: front of the neck, about 10 cm below the head's origin (procedural rig layout).
    point = rest_larynx_point(builtin_rig)
    assert -12.0 < float(point[1]) < -8.0 and float(point[2]) > 4.0 and abs(float(point[0])) < 1e-3


def test_larynx_point_slides_up_with_tau_and_ignores_eta(builtin_rig):
    tau = torch.tensor([0.0, 0.03, 0.03])
    eta = torch.tensor([1.0, 1.0, 0.6])
    vertices = builtin_rig(builtin_rig.neutral(3), tau=tau, eta=eta)
    points = larynx_point(builtin_rig, vertices, tau, larynx_areas(builtin_rig))
    rise = float(points[1, 1] - points[0, 1])
    assert 0.8 < rise < 1.3                                  # tau 0.03 ~ 1 cm (models/rig.py)
    # eta shrinks the bump towards the neck along the larynx direction only: the point moves < 0.3 cm.
    assert float((points[2] - points[1]).norm()) < 0.3


@pytest.mark.parametrize("suffix,bits,tolerance", [(".png", 8, 1.0 / 255), (".png", 16, 1.0 / 65535 + 1e-6),
                                                  (".exr", 8, 1e-6)])
def test_normal_image_files_round_trip(tmp_path, suffix, bits, tolerance):
    rng = np.random.default_rng(0)
    normals = rng.normal(size=(20, 30, 3)).astype(np.float32)
    normals /= np.linalg.norm(normals, axis=-1, keepdims=True)
    normals[:4] = 0.0                                            # background
    path = tmp_path / f"n{suffix}"
    write_normal_image(path, normals, bits)
    values, is_float = read_normal_image(path)
    assert values.shape == (20, 30, 3)
    expected = normals if is_float else encode_normals(normals)
    assert is_float == (suffix == ".exr")
    assert float(np.abs(values - expected).max()) <= tolerance
    if not is_float:
        assert float(values[:4].max()) == 0.0                  # background written black


def test_stored_values_map_to_the_unit_range():
    """Integers over their type's maximum (255, 65535), floats untouched, signed integers refused."""
    values, is_float = stored_to_unit(np.array([0, 51, 255], np.uint8))
    assert not is_float and values.dtype == np.float32 and np.allclose(values, [0.0, 0.2, 1.0], atol=1e-7)
    values, is_float = stored_to_unit(np.array([0, 13107, 65535], np.uint16), dtype=np.float64)
    assert not is_float and values.dtype == np.float64 and np.allclose(values, [0.0, 0.2, 1.0], atol=1e-12)
    values, is_float = stored_to_unit(np.array([-0.5, 0.25], np.float64))
    assert is_float and values.dtype == np.float32 and np.array_equal(values, [-0.5, 0.25])
    with pytest.raises(InputError, match=r"k\.npy: pixel type int16, expected unsigned integers"):
        stored_to_unit(np.zeros(3, np.int16), "k.npy")


def test_read_normal_image_errors(tmp_path):
    with pytest.raises(InputError, match="not found"):
        read_normal_image(tmp_path / "missing.png")
    (tmp_path / "bad.png").write_bytes(b"not a png")
    with pytest.raises(InputError, match="bad.png: not a readable image"):
        read_normal_image(tmp_path / "bad.png")
    (tmp_path / "x.jpg").write_bytes(b"")
    with pytest.raises(InputError, match="unsupported image format"):
        read_normal_image(tmp_path / "x.jpg")


def test_sequence_is_deterministic_and_its_truth_follows_tau(builtin_rig):
    config = SequenceConfig(frames=24, size=96, cm_per_px=0.2, swallows_per_minute=60.0, head_motion_deg=0.0,
                            noise=0.05)
    a = make_sequence(builtin_rig, config, seed=5)
    b = make_sequence(builtin_rig, config, seed=5)
    c = make_sequence(builtin_rig, config, seed=6)
    assert np.array_equal(a.normals, b.normals) and np.array_equal(a.larynx_px, b.larynx_px)
    assert not np.array_equal(a.normals, c.normals)
    assert a.normals.shape == (24, 96, 96, 3) and a.larynx_px.shape == (24, 2)
    norms = np.linalg.norm(a.normals[a.mask], axis=-1)
    assert np.allclose(norms, 1.0, atol=1e-5)                     # noise is renormalised
    assert float(np.abs(a.normals[~a.mask]).max()) == 0.0
    # No head motion: the truth moves straight up, linearly in tau (the rig's px per tau at 0.2 cm/px).
    assert np.allclose(a.larynx_px[:, 0], a.larynx_px[0, 0], atol=1e-3)
    slope = np.polyfit(a.tau, a.larynx_px[:, 1], 1)[0]
    assert -230 < slope < -140                                    # ~35 cm per tau unit / 0.2 cm per px


def test_head_motion_is_smooth_and_within_its_amplitude():
    theta = head_motion(300, 30.0, seed=1, amplitude_deg=3.0, max_hz=0.3)
    assert theta.shape == (300, 8, 3)
    head = np.degrees(theta.sum(axis=1))                         # the joints' share summed: the head's turn
    assert float(np.abs(head).max()) <= 3.0 + 1e-9 and float(np.abs(head).max()) > 1.0
    assert float(np.abs(np.diff(head, axis=0)).max()) < 0.3       # degrees per frame: smooth


def test_sequence_yaml_mirrors_config_dataclass():
    """configs/normal_sequences.yaml holds every SequenceConfig field with the dataclass's default, and the
    CLI's own keys besides."""
    with open(Path(__file__).resolve().parents[1] / "configs" / "normal_sequences.yaml") as f:
        config = yaml.safe_load(f)
    cli_keys = {"defaults", "out", "format", "seed", "rig", "threads"}
    assert {k: v for k, v in config.items() if k not in cli_keys} == dataclasses.asdict(SequenceConfig())


def test_sequence_folder_of_an_earlier_run_is_refused(tmp_path, builtin_rig):
    """A second sequence written over a first would leave its extra frames beside the new truth.csv."""
    sequence = make_sequence(builtin_rig, SequenceConfig(frames=3, size=64, cm_per_px=0.32), seed=0)
    written = write_sequence(tmp_path / "seq", sequence, "png8")
    assert [p.name for p in written] == ["frame_00000.png", "frame_00001.png", "frame_00002.png"]
    with pytest.raises(InputError, match=r"out=.*seq: already holds 4 output file\(s\) of an earlier run "
                                         r"\(frame_00000\.png, frame_00001\.png, frame_00002\.png, \.\.\.\)"):
        write_sequence(tmp_path / "seq", sequence, "npy")
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match=r"out=.*file: not a folder"):
        write_sequence(tmp_path / "file", sequence, "npy")
    with pytest.raises(InputError, match=r"format=jpg: expected png8, png16, exr, npy"):
        write_sequence(tmp_path / "other", sequence, "jpg")
    assert not (tmp_path / "other").exists()
