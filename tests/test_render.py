"""Normal-map renderer (scene/render.py), normal-map files (data/normals.py) and synthetic sequences
(scene/normal_sequences/__init__.py).

The renderer is checked against analytic surfaces (a plane; a sphere, each pixel's ray intersected with it
in closed form), its projection against its own rasterised depth, the encoding against its definition
(n + 1) / 2 on disk, EXR files as other tools write them, and the sequences' truth against the built-in
rig's construction (its UV height is linear in world height: 33.5 cm per UV unit).
"""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import OpenEXR
import pytest
import torch

from base.errors import InputError
from base.tables import CsvTable
from data.expressions import EXPRESSION_NAMES, read_expressions
from data.normals import encode_normals, read_normal_image, stored_to_unit, write_normal_image
from data.procedural_rig import Y_BOTTOM, Y_TOP
from scene.normal_sequences import SequenceConfig, head_motion, make_sequence, tau_r2, write_sequence
from scene.render import (
    Camera,
    NeckRenderer,
    larynx_areas,
    larynx_point,
    neck_camera,
    outward_faces,
    render_normals,
    rest_larynx_point,
)

REPO = Path(__file__).resolve().parents[1]
CM_PER_UV = Y_TOP - Y_BOTTOM     # the built-in rig's v runs linearly from Y_BOTTOM to Y_TOP (world cm)


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
def test_sphere_normals_match_the_closed_form_ray_sphere_intersection(perspective):
    radius, centre = 3.0, np.array([0.4, -0.3, 0.0])
    vertices, faces = uv_sphere(radius, tuple(centre))
    camera = Camera(centre=(0.0, 0.0, 0.0), width=96, height=96, cm_per_px=0.08, perspective=perspective,
                    distance=30.0)
    render = render_normals(vertices, faces, camera)
    # Each pixel centre's ray, in camera space (the eye at the origin looking along -z; the world centre
    # (0, 0, 0) is at (0, 0, -distance)): orthographic rays run along -z from (x, y, 0), perspective ones
    # leave the eye towards (x, y, -focal) in pixel units.  Nearest root of |o + t d - c|^2 = r^2.
    rows, cols = np.mgrid[0:96, 0:96].astype(np.float64)
    cx, cy = camera.principal_point
    sphere = centre - np.array([0.0, 0.0, camera.distance])
    if perspective:
        origin = np.zeros((96, 96, 3))
        direction = np.stack([cols - cx, cy - rows, np.full_like(rows, -camera.focal_px)], -1)
    else:
        origin = np.stack([(cols - cx) * camera.cm_per_px, (cy - rows) * camera.cm_per_px, np.zeros_like(rows)], -1)
        direction = np.broadcast_to([0.0, 0.0, -1.0], (96, 96, 3))
    direction = direction / np.linalg.norm(direction, axis=-1, keepdims=True)
    to_origin = origin - sphere
    b_half = (direction * to_origin).sum(-1)
    disc = b_half ** 2 - ((to_origin ** 2).sum(-1) - radius ** 2)
    hit = disc > 0
    t = -b_half - np.sqrt(np.where(hit, disc, 0.0))
    analytic = (origin + t[..., None] * direction - sphere) / radius            # unit normals, camera space
    mask = render.mask[0].numpy()
    # Silhouette: the rendered pixels are the rays that hit, but for the faceted rim (a 64 x 128 sphere).
    assert (mask != hit).sum() < 0.01 * hit.sum()
    both = mask & hit & (analytic[..., 2] > 0.3)                             # away from the silhouette
    normals = render.normals[0].numpy()[both]
    angle = np.degrees(np.arccos(np.clip((normals * analytic[both]).sum(-1), -1, 1)))
    # Interpolated vertex normals of a 64 x 128 sphere: within a fraction of its 2.8-degree facets.
    assert float(np.median(angle)) < 0.3 and float(angle.max()) < 1.5
    # The depth, too, is the intersection's: cm in front of the eye along the viewing axis.
    depth = render.depth[0].numpy()[both]
    assert float(np.abs(depth - (-(origin + t[..., None] * direction)[..., 2])[both]).max()) < 0.02


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
    assert rise == pytest.approx(0.03 * CM_PER_UV, rel=0.015)     # the map slides along v, linear in height
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
    # No head motion: the truth moves straight up, linearly in tau: the built-in rig's map slides along its
    # UV height, linear in world height at CM_PER_UV cm per unit, seen at 0.2 cm per px.  The larynx point
    # is a centroid over the mesh's vertex rows (0.7 cm apart), which its slide resamples: within 1.5 %.
    assert np.allclose(a.larynx_px[:, 0], a.larynx_px[0, 0], atol=1e-3)
    slope = np.polyfit(a.tau, a.larynx_px[:, 1], 1)[0]
    assert slope == pytest.approx(-CM_PER_UV / 0.2, rel=0.015)
    # With the head still and no expressions the slide is the truth, and the ceiling is near 1.
    assert np.array_equal(a.slide_px, a.larynx_px) and a.ceiling_r2() > 0.999


def test_head_motion_is_smooth_and_within_its_amplitude():
    theta = head_motion(300, 30.0, seed=1, amplitude_deg=3.0, max_hz=0.3)
    assert theta.shape == (300, 8, 3)
    head = np.degrees(theta.sum(axis=1))                         # the joints' share summed: the head's turn
    assert float(np.abs(head).max()) <= 3.0 + 1e-9 and float(np.abs(head).max()) > 1.0
    assert float(np.abs(np.diff(head, axis=0)).max()) < 0.3       # degrees per frame: smooth


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


# --------------------------------------------------------------------------- EXR files of other tools


def write_exr(path: Path, channels: dict) -> None:
    with OpenEXR.File({"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage},
                      {k: np.ascontiguousarray(v) for k, v in channels.items()}) as exr:
        exr.write(str(path))


@pytest.fixture
def unit_normals():
    rng = np.random.default_rng(1)
    normals = rng.normal(size=(12, 10, 3)).astype(np.float32)
    return normals / np.linalg.norm(normals, axis=-1, keepdims=True)


def test_exr_written_by_other_tools(tmp_path, unit_normals):
    """Separate R/G/B channels in half floats, RGBA, and one layer's <layer>.R/G/B (a compositor's pass)."""
    n = unit_normals
    half = {c: n[..., k].astype(np.float16) for k, c in enumerate("RGB")}
    write_exr(tmp_path / "half.exr", half)
    values, is_float = read_normal_image(tmp_path / "half.exr")
    assert is_float and values.dtype == np.float32 and values.shape == (12, 10, 3)
    assert float(np.abs(values - n).max()) <= 2.0 ** -11         # half precision: 11 significant bits
    write_exr(tmp_path / "rgba.exr", {"RGBA": np.concatenate([n, np.full((12, 10, 1), 0.5, np.float32)], -1)})
    assert np.array_equal(read_normal_image(tmp_path / "rgba.exr")[0], n)          # alpha dropped
    layered = {f"normal.{c}": n[..., k] for k, c in enumerate("RGB")} | {"depth.Z": n[..., 0], "A": n[..., 1]}
    write_exr(tmp_path / "layer.exr", layered)
    assert np.array_equal(read_normal_image(tmp_path / "layer.exr")[0], n)


def test_exr_errors_name_the_file_and_what_was_expected(tmp_path, unit_normals):
    write_exr(tmp_path / "depth.exr", {"Z": unit_normals[..., 0]})
    with pytest.raises(InputError, match=r"depth\.exr: EXR channels Z; expected R, G, B channels"):
        read_normal_image(tmp_path / "depth.exr")
    two = {f"{layer}.{c}": unit_normals[..., k] for layer in ("a", "b") for k, c in enumerate("RGB")}
    write_exr(tmp_path / "two.exr", two)
    with pytest.raises(InputError, match=r"two\.exr: EXR layers a, b: give a file with one"):
        read_normal_image(tmp_path / "two.exr")
    (tmp_path / "bad.exr").write_bytes(b"not an exr")
    with pytest.raises(InputError, match=r"bad\.exr: not a readable EXR image"):
        read_normal_image(tmp_path / "bad.exr")


# --------------------------------------------------------------------------- sequences


def test_tau_r2_is_the_squared_correlation_of_a_linear_fit():
    rng = np.random.default_rng(0)
    tau = rng.normal(size=200)
    assert tau_r2(tau, 3.0 - 400.0 * tau) == pytest.approx(1.0)            # any affine map of tau
    noisy = 400.0 * tau + rng.normal(scale=400.0, size=200)                # noise as large as the signal
    fit = np.polyval(np.polyfit(noisy, tau, 1), noisy)
    expected = 1.0 - ((tau - fit) ** 2).sum() / ((tau - tau.mean()) ** 2).sum()
    assert tau_r2(tau, noisy) == pytest.approx(expected, abs=1e-12) and 0.3 < expected < 0.7
    assert tau_r2(tau, np.full(200, 2.0)) == 0.0


def write_hack_expressions(path: Path, weights: np.ndarray, fps: float) -> None:
    """A HACK-named expression CSV with a time column (the format data.expressions reads)."""
    header = ",".join(["time", *EXPRESSION_NAMES])
    rows = [",".join([f"{i / fps:.6f}", *(f"{v:.6f}" for v in row)]) for i, row in enumerate(weights)]
    path.write_text(header + "\n" + "\n".join(rows) + "\n")


def test_sequence_replays_an_expression_recording(tmp_path, builtin_rig):
    """The face replays the recording from expression_start, resampled to the sequence's fps, looping."""
    fps_recording, frames = 20.0, 50
    weights = np.zeros((40, len(EXPRESSION_NAMES)))
    jaw = EXPRESSION_NAMES.index("jawOpen")
    weights[:, jaw] = np.linspace(0.0, 0.78, 40)                          # 0.02 per recorded frame
    write_hack_expressions(tmp_path / "take.csv", weights, fps_recording)
    config = SequenceConfig(frames=frames, fps=30.0, size=64, cm_per_px=0.32, noise=0.0, head_motion_deg=0.0,
                            expressions=str(tmp_path / "take.csv"), expression_start=0.5)
    seq = make_sequence(builtin_rig, config, seed=0)
    assert seq.psi.shape == (frames, builtin_rig.num_expressions)
    # 40 recorded frames at 20 fps span 1.95 s: 59 frames at 30 fps (0 to 1.93 s); from 0.5 s (frame 15) the
    # window runs to frame 58, then loops to the recording's start.
    time = (15 + np.arange(frames)) % 59 / 30.0
    np.testing.assert_allclose(seq.psi[:, jaw], 0.02 * time * fps_recording, atol=1e-5)
    others = np.delete(seq.psi, jaw, axis=1)
    assert float(np.abs(others).max()) == 0.0
    with pytest.raises(InputError, match=r"expression_start=9: outside the recording .*take\.csv \(0\.\.1\.93 s\)"):
        make_sequence(builtin_rig, SequenceConfig(**{**config.__dict__, "expression_start": 9.0}), seed=0)
    with pytest.raises(InputError, match=r"missing\.csv: file not found"):
        make_sequence(builtin_rig, SequenceConfig(**{**config.__dict__, "expressions": str(tmp_path / "missing.csv")}),
                      seed=0)


def test_sequence_from_a_live_link_face_take(builtin_rig, livelinkface_samples):
    """A real recording, read where it is: the window is the take's, resampled; the seed picks its start."""
    take = livelinkface_samples[0]
    recording = read_expressions(take).resampled(30.0)
    config = SequenceConfig(frames=40, size=64, cm_per_px=0.32, noise=0.0, head_motion_deg=0.0, expressions=str(take))
    a, b = make_sequence(builtin_rig, config, seed=1), make_sequence(builtin_rig, config, seed=2)
    starts = []
    for seq in (a, b):
        errors = [np.abs(recording.psi[s:s + 40] - seq.psi).max() for s in range(len(recording) - 40)]
        starts.append(int(np.argmin(errors)))
        assert min(errors) < 1e-6                                  # exactly a window of the take
    assert starts[0] != starts[1]


def test_normal_sequences_runs_as_a_command(tmp_path):
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    out = tmp_path / "seq"
    result = subprocess.run([sys.executable, "-m", "scene.normal_sequences", f"out={out}", "frames=4", "size=64",
                             "cm_per_px=0.32", "format=npy", "seed=3", "head_motion_deg=0"], cwd=tmp_path, env=env,
                            capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr
    assert "rendered 4 frames of 64x64" in result.stdout
    stack = np.load(out / "normals.npy")
    assert stack.shape == (4, 64, 64, 3) and stack.dtype == np.float32
    truth = CsvTable(out / "truth.csv")
    assert truth.header == ["frame", "time", "tau", "x_px", "y_px", "slide_x_px", "slide_y_px", "eta", "fps"]
    np.testing.assert_allclose(truth.numeric("time"), np.arange(4) / 30.0)
    # Bad input: exit status 2 and one line naming the key, nothing written.
    for args, message in ((["format=jpg"], "format=jpg: expected png8, png16, exr, npy"),
                          (["framez=3"], "framez"), (["frames=many"], "frames")):
        bad = subprocess.run([sys.executable, "-m", "scene.normal_sequences", f"out={tmp_path / 'bad'}", *args],
                             cwd=tmp_path, env=env, capture_output=True, text=True, timeout=300)
        assert bad.returncode == 2 and message in bad.stderr and "Traceback" not in bad.stderr
        assert not (tmp_path / "bad").exists()
