"""Face video with known answers, for the face stage's tests and benchmark: the ICT-FaceKit head rendered as a
shaded RGB image (``tests/test_face_video.py``, ``benchmarks/bench_face_video.py``).

:class:`FaceHead` reads ICT-FaceKit's ``FaceXModel`` (the neutral mesh and the expression OBJs it is asked
for; never copied, read where it lies) and renders it with given expression weights and head rotation.

- Mesh: all ICT materials but the transparent layers (lacrimal fluid, eye blend, eye occlusion) and the
  iris spheres, which coincide with the sclera; the iris and pupil are painted on the sclera instead
  (vertices within :data:`IRIS_DEGREES` / :data:`PUPIL_DEGREES` of the eyeball's forward axis), the lips
  where ICT's ``mouthPucker`` shape moves the skin most.
- Geometry: ICT's frame (cm, y up, face towards +z, x to the subject's left) is the rig's world frame;
  the head turns by ``rotation`` [3,3] about :data:`PIVOT` (near the top of the neck).
- Camera: ``scene.render.Camera`` (x right, y up, z towards the camera), perspective, looking at the face
  from +z, so image right is the subject's left (a photo, not a mirror).
- Shading: Lambert, one directional light from the camera's upper left plus ambient, drawn two-sided
  (the normal turned towards the eye) so the winding of ICT's separate parts does not matter.
"""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import torch

from base.rotations import ypr_to_matrix
from data.expressions import EXPRESSION_NAMES
from data.mesh_io import read_obj
from scene.render import Camera, rasterize, vertex_normals

SKIPPED_MATERIALS = ("M_LacrimalFluid", "M_EyeBlend", "M_EyeOcclusion", "M_IrisLeft", "M_IrisRight")
ALBEDO = {  # RGB in [0, 1]
    "M_Face": (0.86, 0.66, 0.55), "M_BackHead": (0.30, 0.22, 0.16), "M_GumsTongue": (0.55, 0.22, 0.22),
    "M_Teeth": (0.92, 0.90, 0.82), "M_ScleraLeft": (0.95, 0.95, 0.93), "M_ScleraRight": (0.95, 0.95, 0.93),
    "M_EyeLashes": (0.08, 0.06, 0.05),
}
IRIS_RGB, PUPIL_RGB, LIP_RGB = (0.30, 0.20, 0.12), (0.03, 0.03, 0.03), (0.70, 0.38, 0.38)
LIP_SHARE = 0.75
IRIS_DEGREES, PUPIL_DEGREES = 32.0, 13.0   # half-angle of the iris / pupil seen from the eyeball's centre
PIVOT = (0.0, -8.0, 0.0)                   # cm, about where the head turns on the neck
LIGHT = (-0.4, 0.5, 1.0)                   # towards the light, camera frame
AMBIENT = 0.35
BACKGROUND = (0.55, 0.60, 0.65)
# cm from the eye to the face: with the 28 cm wide view, a vertical field of view of 63 degrees, the one
# MediaPipe's face geometry assumes (its default perspective camera), so its pose is not biased by a
# focal length it does not know (at 60 cm, 26 degrees, yaw came out 2-3 degrees smaller).
CAMERA_DISTANCE = 23.0


def _faces_by_material(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Triangles [F,3] (0-based, quads split) and their material names [F] from an OBJ's usemtl groups."""
    material, triangles, names = "", [], []
    for line in path.read_bytes().splitlines():
        if line.startswith(b"usemtl"):
            material = line.split()[1].decode()
        elif line.startswith(b"f ") and material not in SKIPPED_MATERIALS:
            corners = [int(c.split(b"/")[0]) - 1 for c in line.split()[1:]]
            for i in range(1, len(corners) - 1):
                triangles.append((corners[0], corners[i], corners[i + 1]))
                names.append(material)
    return np.asarray(triangles, dtype=np.int64), np.asarray(names)


class FaceHead:
    """The ICT-FaceKit head: ``render(weights, rotation)`` -> RGB uint8 [H,W,3].

    ``weights`` maps HACK expression names (``data.expressions.EXPRESSION_NAMES``) to weights; only the
    names given at construction (``expressions``) can be used.
    """

    def __init__(self, ict_dir: str | Path, expressions: tuple[str, ...] = (), size: int = 256,
                 cm_per_px: float | None = None, distance: float = CAMERA_DISTANCE):
        model_dir = Path(ict_dir) / "FaceXModel" if (Path(ict_dir) / "FaceXModel").is_dir() else Path(ict_dir)
        neutral_path = model_dir / "generic_neutral_mesh.obj"
        self.neutral = torch.tensor(read_obj(neutral_path, vertices_only=True).vertices, dtype=torch.float32)
        unknown = [name for name in expressions if name not in EXPRESSION_NAMES]
        if unknown:
            raise ValueError(f"expressions {unknown}: not HACK expression names")
        self.deltas = {name: torch.tensor(read_obj(model_dir / f"{name}.obj", vertices_only=True).vertices,
                                          dtype=torch.float32) - self.neutral for name in expressions}
        triangles, materials = _faces_by_material(neutral_path)
        self.triangles = torch.tensor(triangles)                                      # for the normals
        self.faces = torch.tensor(np.concatenate([triangles, triangles[:, [0, 2, 1]]]))  # drawn two-sided
        colours = np.zeros((len(self.neutral), 3), dtype=np.float32)
        for material, rgb in ALBEDO.items():
            colours[np.unique(triangles[materials == material])] = rgb
        for side in ("Left", "Right"):  # iris and pupil painted on the sclera around its forward axis
            ids = np.unique(triangles[materials == f"M_Sclera{side}"])
            points = self.neutral.numpy()[ids]
            centre = (points.min(0) + points.max(0)) / 2
            direction = (points - centre) / np.linalg.norm(points - centre, axis=1, keepdims=True)
            colours[ids[direction[:, 2] > np.cos(np.radians(IRIS_DEGREES))]] = IRIS_RGB
            colours[ids[direction[:, 2] > np.cos(np.radians(PUPIL_DEGREES))]] = PUPIL_RGB
        # Lips: the face vertices mouthPucker moves most (over LIP_SHARE of its largest displacement).
        pucker = read_obj(model_dir / "mouthPucker.obj", vertices_only=True).vertices - self.neutral.numpy()
        moved = np.linalg.norm(pucker, axis=1)
        face_ids = np.unique(triangles[materials == "M_Face"])
        lips = face_ids[moved[face_ids] > LIP_SHARE * moved.max()]
        colours[lips] = LIP_RGB
        self.colours = torch.tensor(colours)
        lo, hi = self.neutral.numpy()[face_ids].min(0), self.neutral.numpy()[face_ids].max(0)
        centre = ((lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2 - 1.0, float(hi[2]))
        self.camera = Camera(centre=centre, width=size, height=size, perspective=True, distance=distance,
                             cm_per_px=cm_per_px if cm_per_px is not None else 28.0 / size)
        self.light = torch.tensor(LIGHT) / torch.linalg.norm(torch.tensor(LIGHT))

    def vertices(self, weights: dict[str, float] | None = None, rotation: np.ndarray | None = None) -> torch.Tensor:
        """Posed vertices [N,3] (cm, world frame): neutral + weighted deltas, turned by ``rotation`` about PIVOT."""
        points = self.neutral.clone()
        for name, weight in (weights or {}).items():
            points += float(weight) * self.deltas[name]
        if rotation is not None:
            pivot = torch.tensor(PIVOT)
            points = (points - pivot) @ torch.as_tensor(rotation, dtype=torch.float32).T + pivot
        return points

    @torch.no_grad()
    def render(self, weights: dict[str, float] | None = None, rotation: np.ndarray | None = None) -> np.ndarray:
        """RGB uint8 [H,W,3] of the head with expression ``weights`` turned by ``rotation`` [3,3] (world frame)."""
        cam_points = self.camera.to_camera(self.vertices(weights, rotation)[None])
        normals = vertex_normals(cam_points, self.triangles)[0]
        pixels, depth = self.camera.project_camera(cam_points)
        fragments = rasterize(pixels, depth, self.faces, self.camera.height, self.camera.width, True)
        corners = self.faces.index_select(0, fragments.face)                           # [P,3]
        bary = fragments.bary[..., None]
        normal = (normals[corners] * bary).sum(1)
        normal = normal / normal.norm(dim=-1, keepdim=True).clamp_min(1e-9)
        normal = torch.where(normal[:, 2:3] < 0, -normal, normal)                      # two-sided
        albedo = (self.colours[corners] * bary).sum(1)
        shade = AMBIENT + (1 - AMBIENT) * (normal @ self.light).clamp_min(0)[:, None]
        image = fragments.dense(albedo * shade, -1.0)[0]
        image = torch.where(image < 0, torch.tensor(BACKGROUND), image)
        return (image.clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()


def write_video(path: str | Path, frames, fps: float, fourcc: str = "mp4v") -> Path:
    """RGB uint8 frames [H,W,3] (an iterable) into a video file at ``fps`` (OpenCV's writer, ``fourcc``)."""
    path = Path(path)
    writer = None
    try:
        for rgb in frames:
            if writer is None:
                writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), fps, (rgb.shape[1], rgb.shape[0]))
                if not writer.isOpened():
                    raise RuntimeError(f"{path}: OpenCV cannot write {fourcc} video")
            writer.write(np.ascontiguousarray(rgb[..., ::-1]))
    finally:
        if writer is not None:
            writer.release()
    return path


def known_motion(count: int, fps: float, yaw_degrees: float = 20.0,
                 pitch_degrees: float = 12.0) -> dict[str, np.ndarray]:
    """Expression weights and head angles [count] with known values: jawOpen, eyeBlink (both eyes) and
    mouthPucker rising and falling at different times (a smooth bump each, so they rarely coincide), yaw
    and pitch (radians) slow sinusoids of different periods."""
    time = np.arange(count) / fps
    phase = time / max(time[-1], 1e-9)

    def bumps(centres: tuple[float, ...], width: float) -> np.ndarray:
        return np.clip(sum(np.exp(-0.5 * ((phase - c) / width) ** 2) for c in centres), 0, 1)

    return {
        "jawOpen": 0.8 * bumps((0.15, 0.65), 0.06),
        "eyeBlink": bumps((0.35, 0.85), 0.04),
        "mouthPucker": 0.9 * bumps((0.45,), 0.07) + 0.9 * bumps((0.95,), 0.04),
        "yaw": np.radians(yaw_degrees) * np.sin(2 * np.pi * phase),
        "pitch": np.radians(pitch_degrees) * np.sin(2 * np.pi * 1.5 * phase + 0.7),
    }


def render_known_motion(head: FaceHead, motion: dict[str, np.ndarray], noise: float = 0.0, seed: int = 0):
    """Frames (RGB uint8) of ``head`` following :func:`known_motion`, with Gaussian sensor noise of standard
    deviation ``noise`` (in 0-255 levels); the head needs jawOpen, eyeBlink_L/R and mouthPucker."""
    rng = np.random.default_rng(seed)
    ypr = np.stack([motion["yaw"], motion["pitch"], np.zeros_like(motion["yaw"])], axis=1)
    rotations = ypr_to_matrix(torch.tensor(ypr, dtype=torch.float32)).numpy()
    for t in range(len(ypr)):
        weights = {"jawOpen": motion["jawOpen"][t], "eyeBlink_L": motion["eyeBlink"][t],
                   "eyeBlink_R": motion["eyeBlink"][t], "mouthPucker": motion["mouthPucker"][t]}
        rgb = head.render(weights, rotations[t])
        if noise > 0:
            rgb = np.clip(rgb + rng.normal(0, noise, rgb.shape), 0, 255).astype(np.uint8)
        yield rgb
