"""The web viewer (scene.viewer): one offline ``viewer.html`` with the clip's GLB embedded, and the page itself
in a real browser.

Without a browser: the page is one file, loads nothing from the network, embeds the GLB the exporter writes,
is written atomically, and ``export=[html]`` writes it from ``infer.py`` and ``motion.retarget``.  With Debian's
``chromium`` and Python ``playwright`` (driven with ``executable_path``; ``.ci/run`` installs chromium): at
several times the bone rotations and expression weights the page applied equal the params within 1e-4, play
and pause move the clock, the range input scrubs, a live-style ``applyFrame`` poses the character, and a
screenshot shows a lit (not black) character whose silhouette is the rig's own, projected with the page's
camera (IoU >= 0.8).  Skipped, with the reason, where either is missing.
"""
from __future__ import annotations

import base64
import io
import json
import re
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch

from base.cli import compose_config, run_cli
from base.files import atomic_path, write_csv
from data.params import AnimationParams, rig_checksum, save_params
from models.rig import HeadNeckModel
from scene.viewer import build as viewer_build
from scene.viewer import build_viewer, glb_bytes
from tests.browser import headless_chromium

TOLERANCE = 1e-4
BACKGROUND = np.array([0x1E, 0x22, 0x28])   # the page's scene background
# Strings that look like URLs but are never fetched: the XHTML namespace three.js passes to createElementNS.
NOT_LOADED = {"http://www.w3.org/1999/xhtml"}


def clip(rig: HeadNeckModel, frames: int = 30, fps: float = 30.0, seed: int = 0) -> AnimationParams:
    """Nods, turns and tilts at every joint (different per joint), sparse expressions, a sliding larynx."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / fps
    phase = np.linspace(0, 2 * np.pi, frames)[:, None]
    scale = np.linspace(0.5, 1.5, rig.num_joints)[None]
    anatomical = np.stack([0.09 * scale * np.sin(phase), 0.07 * scale * np.sin(2 * phase + 0.4),
                           0.05 * scale * np.cos(phase)], axis=-1)
    theta = rig.from_anatomical(torch.tensor(anatomical, dtype=torch.float32))
    names = rig.expression_names
    psi = rng.uniform(0, 0.9, (frames, len(names))) * (rng.uniform(size=len(names)) < 0.4)
    with torch.no_grad():
        head = rig.head_rotation(theta)
    return AnimationParams(time=t, fps=fps, psi=psi, tau=0.025 * np.sin(1.5 * phase[:, 0]),
                           eta=1.0 + 0.2 * np.sin(phase[:, 0]), theta=theta.numpy(), head_rotation=head.numpy(),
                           joint_names=rig.joint_names, expression_names=names, rig_checksum=rig_checksum(rig.rig))


def theta_quaternions(theta: np.ndarray) -> np.ndarray:
    """Axis-angle [...,3] -> unit quaternions (x, y, z, w) [...,4], w >= 0 for angles below pi."""
    theta = np.asarray(theta, np.float64)
    angle = np.linalg.norm(theta, axis=-1, keepdims=True)
    axis = np.where(angle > 1e-12, theta / np.maximum(angle, 1e-12), 0.0)
    return np.concatenate([axis * np.sin(angle / 2), np.cos(angle / 2)], axis=-1)


def embedded_glb(html: str) -> bytes:
    match = re.search(r'<script type="application/octet-stream" id="hackneck-glb">([^<]*)</script>', html)
    assert match, "no embedded GLB"
    return base64.b64decode(match.group(1).strip())


@pytest.fixture(scope="module")
def viewer(builtin_rig, tmp_path_factory):
    """(params, path of viewer.html) for a 30-frame clip on the built-in rig."""
    params = clip(builtin_rig)
    path = tmp_path_factory.mktemp("viewer") / "viewer.html"
    build_viewer(params, builtin_rig, path)
    return params, path


# ----------------------------------------------------------------------------- without a browser


def test_page_is_one_offline_file_embedding_the_glb(builtin_rig, viewer):
    params, path = viewer
    assert sorted(p.name for p in path.parent.iterdir()) == ["viewer.html"]      # one file, nothing beside it
    html = path.read_text(encoding="utf-8")
    # nothing fetched: no external scripts, styles, images, frames or imports; no URL but a namespace
    assert not re.search(r"<(script|link|img|iframe|source)\b[^>]*\b(src|href)\s*=", html, re.IGNORECASE)
    assert not re.search(r"""\bimport\s*\(?\s*["']https?:""", html)
    urls = set(re.findall(r"https?://[^\s\"'<>()]+", html))
    assert urls <= NOT_LOADED, urls - NOT_LOADED
    glb = embedded_glb(html)
    assert glb[:4] == b"glTF" and glb == glb_bytes(params, builtin_rig)
    header = json.loads(re.search(r'id="hackneck-header">([^<]*)</script>', html).group(1))
    assert header["joints"] == list(params.joint_names) and header["frames"] == len(params)
    theta = np.frombuffer(base64.b64decode(header["data"]["theta"]), "<f4").reshape(params.theta.shape)
    assert np.array_equal(theta, params.theta)
    assert "three.js" in html and (viewer_build.VENDOR / "LICENSE").read_text().startswith("The MIT License")


def test_page_embeds_a_given_glb_and_is_written_atomically(builtin_rig, tmp_path, monkeypatch):
    params = clip(builtin_rig, frames=5)
    save_params(tmp_path / "params.npz", params)
    glb = tmp_path / "anim.glb"
    glb.write_bytes(glb_bytes(params, builtin_rig))
    out = tmp_path / "viewer.html"
    out.write_text("old")
    seen = []

    @contextmanager
    def watched(target):
        with atomic_path(target) as tmp:
            yield tmp
            seen.append((Path(tmp).name, out.read_text()))         # written beside it, the old page intact
    monkeypatch.setattr(viewer_build, "atomic_path", watched)
    build_viewer(tmp_path / "params.npz", None, out, glb=glb)      # the rig recorded in the params
    assert len(seen) == 1 and seen[0][1] == "old" and seen[0][0] != "viewer.html"
    assert embedded_glb(out.read_text(encoding="utf-8")) == glb.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["anim.glb", "params.npz", "viewer.html"]


def test_infer_and_retarget_export_html(builtin_rig, tmp_path):
    from infer import run as infer_run
    from motion.retarget import run as retarget_run

    frames = 10
    time = np.arange(frames) / 30.0
    write_csv(tmp_path / "take.csv", {"time": time, "jawOpen": 0.3 + 0.2 * np.sin(5 * time),
                                      "HeadYaw": 0.3 * np.sin(time), "HeadPitch": np.full(frames, 0.1),
                                      "HeadRoll": np.zeros(frames)}, float_format="%.9g")
    out = tmp_path / "infer"
    infer_run(compose_config("infer", [f"expressions={tmp_path / 'take.csv'}", f"out_dir={out}", "checkpoint=none",
                                       "head2neck=none", "plot=false", "allow_missing=true", "export=[glb,html]"]))
    assert embedded_glb((out / "viewer.html").read_text(encoding="utf-8")) == (out / "anim.glb").read_bytes()
    retargeted = tmp_path / "giraffe"
    run_cli("retarget", retarget_run, argv=[f"source={out / 'params.npz'}", "character=giraffe",
                                            f"out_dir={retargeted}", "meshes=false", "export=[html]"])
    assert embedded_glb((retargeted / "viewer.html").read_text(encoding="utf-8"))[:4] == b"glTF"


# ----------------------------------------------------------------------------- in a real browser


@pytest.fixture(scope="module")
def browser():
    """One headless Chromium (software WebGL) for the module: playwright's sync API runs one at a time."""
    with headless_chromium() as browser:
        yield browser


@pytest.fixture(scope="module")
def page(viewer, browser):
    """The viewer open in headless Chromium, loaded, paused."""
    _, path = viewer
    page = browser.new_page(viewport={"width": 640, "height": 640})
    errors = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.route(re.compile(r"^https?://"), lambda route: (errors.append(route.request.url), route.abort()))
    page.goto(path.as_uri())
    page.wait_for_function("window.hackneck && (window.hackneck.ready || window.hackneck.error)", timeout=30_000)
    assert page.evaluate("window.hackneck.error") is None
    page.evaluate("window.hackneck.pause()")
    page.errors = errors
    yield page
    page.close()


def check_state(state: dict, params: AnimationParams, frame: int) -> None:
    assert state["frame"] == frame and abs(state["time"] - params.time[frame]) < 1e-9
    expected = theta_quaternions(params.theta[frame])
    for j, name in enumerate(params.joint_names):
        got = np.array(state["bones"][name])
        error = min(np.abs(got - expected[j]).max(), np.abs(got + expected[j]).max())
        assert error < TOLERANCE, (frame, name, got, expected[j])
    morphs = np.array([state["morphs"][name] for name in params.expression_names])
    assert np.abs(morphs - params.psi[frame]).max() < TOLERANCE
    assert abs(state["tau"] - params.tau[frame]) < TOLERANCE and abs(state["eta"] - params.eta[frame]) < TOLERANCE


def test_browser_applies_the_params_at_every_seek(page, viewer):
    params, _ = viewer
    for frame in (0, 7, 16, len(params) - 1):
        check_state(page.evaluate("(t) => window.hackneck.seek(t)", float(params.time[frame])), params, frame)
        check_state(page.evaluate("window.hackneck.state()"), params, frame)     # state() is the last applied
    assert not page.errors


def test_browser_play_pause_and_scrub(page, viewer):
    params, _ = viewer
    page.evaluate("window.hackneck.seek(0)")
    page.evaluate("window.hackneck.play()")
    page.wait_for_timeout(400)
    page.evaluate("window.hackneck.pause()")
    paused = page.evaluate("window.hackneck.state()")
    assert paused["time"] > 0.1 and paused["frame"] > 2
    page.wait_for_timeout(200)
    assert page.evaluate("window.hackneck.state()")["time"] == paused["time"]          # paused stays put
    # the range input, as a user drags it
    frame = 21
    page.eval_on_selector("#scrub", "(el, t) => { el.value = String(t); el.dispatchEvent(new Event('input')); }",
                          float(params.time[frame]))
    check_state(page.evaluate("window.hackneck.state()"), params, frame)
    # the clip at frame 21 pushed as a live source would (bones / morphs by name) gives the same state
    live = {"time": float(params.time[frame]), "frame": frame, "tau": float(params.tau[frame]),
            "eta": float(params.eta[frame]),
            "bones": {n: q.tolist() for n, q in zip(params.joint_names, theta_quaternions(params.theta[frame]))},
            "morphs": dict(zip(params.expression_names, params.psi[frame].tolist()))}
    page.evaluate("window.hackneck.seek(0)")
    page.evaluate("(f) => window.hackneck.applyFrame(f)", live)
    check_state(page.evaluate("window.hackneck.state()"), params, frame)


def test_browser_shows_a_lit_character(page, viewer):
    from PIL import Image

    params, _ = viewer
    page.evaluate("(t) => window.hackneck.seek(t)", float(params.time[10]))
    page.evaluate("document.getElementById('title').style.display = 'none';"
                  "document.getElementById('status').style.display = 'none'")
    page.wait_for_timeout(200)
    image = np.asarray(Image.open(io.BytesIO(page.locator("#view").screenshot())).convert("RGB"), np.float64)
    character = np.abs(image - BACKGROUND).sum(-1) > 30
    fraction = character.mean()
    assert 0.05 < fraction < 0.7, f"character covers {fraction:.1%} of the view"
    brightness = image[character].mean()
    # (glTF's metallic default, lit without an environment, gives about 112 here; the page gives about 185)
    assert brightness > 145, f"character's mean brightness {brightness:.0f} / 255: not lit"
    # framed: the character's box lies inside the view, away from its edges
    rows, cols = np.flatnonzero(character.any(1)), np.flatnonzero(character.any(0))
    assert rows[0] > 0 and cols[0] > 0 and rows[-1] < image.shape[0] - 1 and cols[-1] < image.shape[1] - 1


def projected_silhouette(rig: HeadNeckModel, params: AnimationParams, frame: int, camera: dict) -> np.ndarray:
    """The rig's mesh at ``frame`` (metres, the GLB's world) projected with the page's camera matrices and
    filled triangle by triangle: a boolean mask [height, width]."""
    import cv2

    from data.mesh_io import triangulate

    with torch.no_grad():
        vertices = rig(torch.as_tensor(params.theta[frame:frame + 1]), torch.as_tensor(params.psi[frame:frame + 1]),
                       torch.as_tensor(params.tau[frame:frame + 1]),
                       torch.as_tensor(params.eta[frame:frame + 1]))[0].double().numpy() / 100.0
    matrix = (np.array(camera["projection"]).reshape(4, 4).T @ np.array(camera["view"]).reshape(4, 4).T
              @ np.array(camera["model"]).reshape(4, 4).T)
    clip_space = np.c_[vertices, np.ones(len(vertices))] @ matrix.T
    ndc = clip_space[:, :2] / clip_space[:, 3:4]
    width, height = camera["width"], camera["height"]
    pixels = np.stack([(ndc[:, 0] + 1) / 2 * width, (1 - ndc[:, 1]) / 2 * height], axis=1)
    mask = np.zeros((height, width), np.uint8)
    shift = 4
    for triangle in triangulate(rig.faces.numpy()):
        cv2.fillConvexPoly(mask, np.round(pixels[triangle] * (1 << shift)).astype(np.int32), 1, cv2.LINE_8, shift)
    return mask.astype(bool)


def test_browser_silhouette_is_the_rigs_projected_with_the_pages_camera(page, viewer, builtin_rig):
    from PIL import Image

    params, _ = viewer
    for frame in (5, 20):
        page.evaluate("(t) => window.hackneck.seek(t)", float(params.time[frame]))
        page.wait_for_timeout(100)
        camera = page.evaluate("window.hackneck.camera()")
        shot = Image.open(io.BytesIO(page.locator("#view canvas").screenshot())).convert("RGB")
        assert shot.size == (camera["width"], camera["height"])
        image = np.asarray(shot, np.float64)
        seen = np.abs(image - BACKGROUND).sum(-1) > 30
        expected = projected_silhouette(builtin_rig, params, frame, camera)
        iou = (seen & expected).sum() / (seen | expected).sum()
        assert expected.mean() > 0.05, "the projected rig must cover part of the view"
        assert iou >= 0.8, f"frame {frame}: silhouette IoU {iou:.3f}"


@pytest.fixture(scope="module")
def pair_page(builtin_rig, tmp_path_factory, browser):
    """The viewer of a giraffe's clip with the human it was retargeted from beside it, open in Chromium."""
    from motion.retarget import default_gains, retarget_params
    from scene.characters import load_character

    human = clip(builtin_rig, seed=4)
    giraffe = HeadNeckModel(load_character("giraffe", builtin_rig.rig))
    params = retarget_params(human, builtin_rig, giraffe, "character:giraffe", default_gains(giraffe))
    path = tmp_path_factory.mktemp("pair") / "viewer.html"
    build_viewer(params, giraffe, path, companion=(human, builtin_rig))
    page = browser.new_page(viewport={"width": 900, "height": 640})
    page.goto(path.as_uri())
    page.wait_for_function("window.hackneck && (window.hackneck.ready || window.hackneck.error)", timeout=30_000)
    assert page.evaluate("window.hackneck.error") is None
    page.evaluate("window.hackneck.pause()")
    yield page, params, giraffe, human
    page.close()


def test_browser_plays_the_giraffe_beside_the_human_on_one_clock(pair_page, builtin_rig):
    from PIL import Image

    page, params, giraffe, human = pair_page
    frame = 12
    state = page.evaluate("(t) => window.hackneck.seek(t)", float(params.time[frame]))
    check_state(state, params, frame)                      # the main character: the giraffe's own params
    check_state(state["companion"], human, frame)          # beside it the human, at the same frame
    assert not np.allclose(params.theta[frame], human.theta[frame], atol=1e-3), "the gains change the giraffe"
    page.evaluate("document.getElementById('title').style.display = 'none';"
                  "document.getElementById('status').style.display = 'none'")
    page.wait_for_timeout(100)
    camera = page.evaluate("window.hackneck.camera()")
    image = np.asarray(Image.open(io.BytesIO(page.locator("#view canvas").screenshot())).convert("RGB"), np.float64)
    seen = np.abs(image - BACKGROUND).sum(-1) > 30
    giraffe_mask = projected_silhouette(giraffe, params, frame, camera)
    human_mask = projected_silhouette(builtin_rig, human, frame, {**camera, "model": camera["companionModel"]})
    expected = giraffe_mask | human_mask
    assert not (giraffe_mask & human_mask).any(), "side by side, not overlapping"
    assert np.flatnonzero(human_mask.any(0)).max() < np.flatnonzero(giraffe_mask.any(0)).min(), "the human on the left"
    iou = (seen & expected).sum() / (seen | expected).sum()
    assert iou >= 0.8, f"silhouette IoU {iou:.3f}"
