"""The built-in procedural head-and-neck rig: HACK's interface, generated in code, no download.

A surface of revolution with elliptical cross-sections (neck widening into
the shoulders, a head with nose, chin and brow), about 5,800 vertices in a
triangulated grid with a cylindrical UV layout (u around the body, the front at
u = 0.5; v up the body), the 8 cervical joints along a lordotic curve,
smooth skinning weights, a 4-component identity shape basis, 55 named expression deltas shaped after what each
ARKit/ICT shape does (jaw rotation about the hinge, lid closure, lip corner
pulls, ...), and a stack of three larynx maps (generic, prominent, low/wide).

Proportions follow an adult head and neck in cm (y up, face towards +z,
x to the subject's left).  Vertebral segment lengths ~1.4-1.8 cm follow
cervical vertebral body heights plus discs (Gilad & Nissan, Spine 11:154-157,
1986, body heights 1.3-1.5 cm, discs 0.4-0.6 cm); the larynx sits on the front
of the neck near C4-C5 (laryngeal prominence at C4-C5: Gray's Anatomy, 41st
ed., ch. 36) and protrudes ~0.9 cm.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.interpolate import PchipInterpolator

from data.assets import JOINT_NAMES, RigData
from data.expressions import EXPRESSION_NAMES

AROUND = 80          # vertices around the body
NECK_ROWS = 60       # rows from the neck base to the crown's start, uniform in height
CAP_ROWS = 12        # rows over the crown, uniform in angle
Y_BOTTOM, Y_CAP, Y_TOP = -19.0, 10.0, 14.5

# Sagittal profile: height (cm) -> centre z, half-width (x) and half-depth (z).
_PROFILE_Y = np.array([-19.0, -15.0, -11.0, -7.0, -4.5, -2.0, 1.0, 4.0, 7.0, 10.0])
_PROFILE_ZC = np.array([-1.0, -0.6, -0.1, 0.3, 1.0, 1.6, 1.5, 1.0, 0.6, 0.2])
_PROFILE_RX = np.array([9.0, 6.4, 5.5, 5.4, 5.8, 6.9, 7.6, 7.8, 7.6, 7.0])
_PROFILE_RZ = np.array([7.5, 5.9, 5.3, 5.4, 6.6, 9.0, 9.9, 10.2, 9.9, 9.2])

# Face features: (x, y, sigma_x, sigma_y, forward displacement in cm).
_FEATURES = [
    (0.0, 2.2, 0.8, 1.7, 1.9),     # nose
    (0.0, -3.4, 1.6, 1.0, 0.5),    # chin
    (0.0, -0.8, 1.6, 0.5, 0.25),   # lips
    (3.2, 5.0, 1.2, 0.9, -0.45),   # eye sockets
    (-3.2, 5.0, 1.2, 0.9, -0.45),
    (0.0, 7.0, 4.0, 0.8, 0.25),    # brow ridge
]

# Cervical chain: segment lengths (cm) and sagittal tilt of each bone from
# vertical (degrees, + = leaning forward): a lordotic curve.
_C7T1_ORIGIN = np.array([0.0, -12.4, -1.6])
_BONE_LENGTHS = np.array([1.80, 1.66, 1.62, 1.66, 1.60, 1.46, 1.42, 10.4])
_BONE_TILT_DEG = np.array([18.0, 15.0, 12.0, 8.0, 2.0, -4.0, -8.0, -12.0])
_SKIN_SOFTNESS = 0.7   # cm, width of the weight transition at each joint
_SKIN_SLANT = 0.3      # a vertex counts as higher by 0.3 * z: the jaw line and neck slope forward

LARYNX_MAP_SIZE = 256
LARYNX_V = 0.265      # UV height of the laryngeal prominence at rest
LARYNX_DIRECTION = np.array([0.0, -0.4, 1.0]) / np.linalg.norm([0.0, -0.4, 1.0])


def _profile(y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return tuple(PchipInterpolator(_PROFILE_Y, values)(np.clip(y, _PROFILE_Y[0], _PROFILE_Y[-1]))
                 for values in (_PROFILE_ZC, _PROFILE_RX, _PROFILE_RZ))


def body_surface() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vertices [N,3], triangles [F,3], vertex UVs [N,2], UV coordinates with a seam column, and
    per-corner UV indices [F,3]."""
    heights = np.concatenate([
        np.linspace(Y_BOTTOM, Y_CAP, NECK_ROWS, endpoint=False),
        Y_CAP + (Y_TOP - Y_CAP) * np.sin(np.linspace(0, np.pi / 2, CAP_ROWS, endpoint=False)),
    ])
    crown = np.concatenate([np.ones(NECK_ROWS), np.cos(np.linspace(0, np.pi / 2, CAP_ROWS, endpoint=False))])
    phi = np.linspace(0, 2 * np.pi, AROUND, endpoint=False)
    zc, rx, rz = _profile(np.minimum(heights, Y_CAP))
    x = (rx * crown)[:, None] * np.sin(phi)[None]
    z = zc[:, None] - (rz * crown)[:, None] * np.cos(phi)[None]
    y = np.broadcast_to(heights[:, None], x.shape)
    # Face features push the front surface forward; fade with how much a vertex faces forward.
    facing = np.clip(-np.cos(phi), 0, None)[None] ** 3
    for fx, fy, sx, sy, amount in _FEATURES:
        z = z + amount * facing * np.exp(-0.5 * (((x - fx) / sx) ** 2 + ((y - fy) / sy) ** 2))
    grid = np.stack([x, y, z], -1).reshape(-1, 3)
    vertices = np.concatenate([grid, [[0.0, Y_TOP, zc[-1]]]])
    rows = len(heights)
    pole = len(vertices) - 1

    index = np.arange(rows * AROUND).reshape(rows, AROUND)
    nxt = np.roll(index, -1, axis=1)
    quads = np.stack([index[:-1], index[1:], nxt[1:], nxt[:-1]], -1).reshape(-1, 4)
    top = np.stack([index[-1], np.full(AROUND, pole), nxt[-1]], -1)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]], top])

    u = phi / (2 * np.pi)
    v = (heights - Y_BOTTOM) / (Y_TOP - Y_BOTTOM)
    vertex_uv = np.concatenate([np.stack(np.meshgrid(u, v), -1).reshape(-1, 2), [[0.5, 1.0]]])
    # Texture coordinates: the grid plus a seam column at u = 1 and the pole.
    uu = np.concatenate([u, [1.0]])
    uv_coords = np.concatenate([np.stack(np.meshgrid(uu, v), -1).reshape(-1, 2), [[0.5, 1.0]]])
    uv_index = np.arange(rows * (AROUND + 1)).reshape(rows, AROUND + 1)
    uv_pole = len(uv_coords) - 1
    uv_quads = np.stack([uv_index[:-1, :-1], uv_index[1:, :-1], uv_index[1:, 1:], uv_index[:-1, 1:]], -1).reshape(-1, 4)
    uv_top = np.stack([uv_index[-1, :-1], np.full(AROUND, uv_pole), uv_index[-1, 1:]], -1)
    faces_uv = np.concatenate([uv_quads[:, [0, 1, 2]], uv_quads[:, [0, 2, 3]], uv_top])
    return vertices, faces, vertex_uv, uv_coords, faces_uv


def cervical_chain() -> tuple[np.ndarray, np.ndarray]:
    """Parents [8] and rest transforms relative to the parent [8,4,4] (bone y axis along the bone)."""
    tilt = np.radians(_BONE_TILT_DEG)
    local = np.tile(np.eye(4), (len(JOINT_NAMES), 1, 1))
    parents = np.arange(len(JOINT_NAMES)) - 1
    for j in range(len(JOINT_NAMES)):
        angle = tilt[j] - (tilt[j - 1] if j else 0.0)
        c, s = np.cos(angle), np.sin(angle)
        local[j, :3, :3] = [[1, 0, 0], [0, c, -s], [0, s, c]]  # about x: the bone leans forward by `angle`
        local[j, :3, 3] = _C7T1_ORIGIN if j == 0 else [0.0, _BONE_LENGTHS[j - 1], 0.0]
    return parents, local


def _joint_origins(local: np.ndarray) -> np.ndarray:
    world = [local[0]]
    for j in range(1, len(local)):
        world.append(world[-1] @ local[j])
    return np.stack(world)[:, :3, 3]


def skinning_weights(vertices: np.ndarray, joint_origins: np.ndarray) -> np.ndarray:
    """[N,J] telescoping logistic weights along a slanted height: bone j owns the band above its joint."""
    height = vertices[:, 1] + _SKIN_SLANT * vertices[:, 2]
    levels = joint_origins[:, 1] + _SKIN_SLANT * joint_origins[:, 2]
    above = 1.0 / (1.0 + np.exp(-(height[:, None] - levels[None, 1:]) / _SKIN_SOFTNESS))  # [N,J-1]
    ones = np.ones((len(vertices), 1))
    zeros = np.zeros((len(vertices), 1))
    return np.concatenate([ones, above], 1) - np.concatenate([above, zeros], 1)


# Expression shapes.  Each ``_L`` entry is mirrored (x -> -x) for ``_R``.
# name: list of (x, y, sigma, (dx, dy, dz)) Gaussian pulls on the face, in cm.
_BROW, _INNER_BROW, _OUTER_BROW = (3.0, 7.2), (1.2, 7.0), (4.6, 6.8)
_UPPER_LID, _LOWER_LID, _EYE = (3.2, 5.6), (3.2, 4.3), (3.2, 5.0)
_CHEEK, _CHEEKBONE = (4.4, 0.5), (4.2, 3.0)
_CORNER, _UPPER_LIP, _LOWER_LIP, _MOUTH = (2.3, -1.0), (0.9, -0.5), (0.9, -1.6), (0.0, -1.0)
_PULLS: dict[str, list] = {
    "browDown_L": [(*_BROW, 1.4, (0.0, -0.45, 0.1)), (*_INNER_BROW, 1.0, (-0.15, -0.3, 0.05))],
    "browInnerUp_L": [(*_INNER_BROW, 1.2, (0.0, 0.55, 0.0))],
    "browOuterUp_L": [(*_OUTER_BROW, 1.3, (0.0, 0.5, 0.0))],
    "cheekPuff_L": [(*_CHEEK, 1.9, (0.55, 0.0, 0.45))],
    "cheekRaiser_L": [(*_CHEEKBONE, 1.5, (0.0, 0.4, 0.2)), (*_LOWER_LID, 0.9, (0.0, 0.15, 0.0))],
    "cheekSquint_L": [(*_CHEEKBONE, 1.1, (0.05, 0.3, 0.1))],
    "eyeBlink_L": [(*_UPPER_LID, 0.8, (0.0, -0.95, 0.08))],
    "eyeLookDown_L": [(*_UPPER_LID, 0.7, (0.0, -0.15, 0.0))],
    "eyeLookIn_L": [(*_EYE, 0.7, (-0.12, 0.0, 0.0))],
    "eyeLookOut_L": [(*_EYE, 0.7, (0.12, 0.0, 0.0))],
    "eyeLookUp_L": [(*_UPPER_LID, 0.7, (0.0, 0.18, 0.0))],
    "eyeSquint_L": [(*_LOWER_LID, 0.8, (0.0, 0.3, 0.0))],
    "eyeWide_L": [(*_UPPER_LID, 0.8, (0.0, 0.35, 0.0))],
    "mouthDimple_L": [(*_CORNER, 0.9, (0.25, 0.0, -0.25))],
    "mouthFrown_L": [(*_CORNER, 1.0, (0.0, -0.45, 0.0))],
    "mouthLowerDown_L": [(*_LOWER_LIP, 0.9, (0.0, -0.4, 0.05))],
    "mouthPress_L": [(_UPPER_LIP[0], -1.0, 1.0, (0.0, 0.0, -0.18))],
    "mouthSmile_L": [(*_CORNER, 1.1, (0.4, 0.5, -0.15))],
    "mouthStretch_L": [(*_CORNER, 1.1, (0.5, -0.2, -0.1))],
    "mouthUpperUp_L": [(*_UPPER_LIP, 0.9, (0.0, 0.35, 0.05))],
    "noseSneer_L": [(1.1, 2.6, 0.8, (0.05, 0.3, 0.1))],
    "mouthClose": [((0.0, -0.5, 1.4, (0.0, -0.2, 0.0))), (0.0, -1.6, 1.4, (0.0, 0.35, 0.0))],
    "mouthFunnel": [(*_MOUTH, 1.3, (0.0, 0.0, 0.4))],
    "mouthPucker": [(*_MOUTH, 1.1, (0.0, 0.0, 0.5)), (2.3, -1.0, 0.8, (-0.3, 0.0, 0.0)),
                    (-2.3, -1.0, 0.8, (0.3, 0.0, 0.0))],
    "mouthLeft": [(*_MOUTH, 1.8, (0.6, 0.0, 0.0))],
    "mouthRight": [(*_MOUTH, 1.8, (-0.6, 0.0, 0.0))],
    "mouthRollLower": [(0.0, -1.6, 1.3, (0.0, 0.1, -0.3))],
    "mouthRollUpper": [(0.0, -0.5, 1.3, (0.0, -0.1, -0.3))],
    "mouthShrugLower": [(0.0, -2.6, 1.4, (0.0, 0.35, 0.1))],
    "mouthShrugUpper": [(0.0, -0.5, 1.3, (0.0, 0.25, 0.05))],
}
_JAW_HINGE = np.array([0.0, 2.5, 1.0])   # temporomandibular joints, on the x axis through this point
_JAW_OPEN_RAD = 0.30
_JAW_SHIFTS = {"jawForward": (0.0, 0.0, 0.5), "jawLeft": (0.5, 0.0, 0.0), "jawRight": (-0.5, 0.0, 0.0)}


def _front_mask(vertices: np.ndarray) -> np.ndarray:
    zc, _, rz = _profile(np.minimum(vertices[:, 1], Y_CAP))
    return np.clip((vertices[:, 2] - zc) / (0.6 * rz), 0.0, 1.0)


def _jaw_mask(vertices: np.ndarray) -> np.ndarray:
    """Lower face: below the lip line, in front, fading out under the chin into the neck."""
    y = vertices[:, 1]
    below_lips = 1.0 / (1.0 + np.exp(-(-1.05 - y) / 0.25))
    above_neck = 1.0 / (1.0 + np.exp(-(y + 6.0) / 0.8))
    return below_lips * above_neck * _front_mask(vertices) ** 0.5


def expression_deltas(vertices: np.ndarray) -> np.ndarray:
    """[55,N,3] deltas in ``EXPRESSION_NAMES`` order."""
    front = _front_mask(vertices)
    face = vertices[front > 0.5]

    def landmark(x: float, y: float) -> np.ndarray:
        return face[np.argmin((face[:, 0] - x) ** 2 + (face[:, 1] - y) ** 2)]

    def pulls(entries) -> np.ndarray:
        delta = np.zeros_like(vertices)
        for x, y, sigma, move in entries:
            d2 = ((vertices - landmark(x, y)) ** 2).sum(1)
            delta += np.exp(-0.5 * d2 / sigma**2)[:, None] * front[:, None] * np.asarray(move)
        return delta

    jaw = _jaw_mask(vertices)
    out = np.zeros((len(EXPRESSION_NAMES), len(vertices), 3))
    for k, name in enumerate(EXPRESSION_NAMES):
        if name == "jawOpen":
            c, s = np.cos(_JAW_OPEN_RAD), np.sin(_JAW_OPEN_RAD)
            rotation = np.array([[1, 0, 0], [0, c, -s], [0, s, c]])  # chin goes down and back
            rel = vertices - _JAW_HINGE
            out[k] = (rel @ rotation.T - rel) * jaw[:, None]
        elif name in _JAW_SHIFTS:
            out[k] = jaw[:, None] * np.asarray(_JAW_SHIFTS[name])
        elif name in _PULLS:
            out[k] = pulls(_PULLS[name])
        elif name.endswith("_R") and name[:-2] + "_L" in _PULLS:
            mirrored = [(-x, y, sigma, (-m[0], m[1], m[2])) for x, y, sigma, m in _PULLS[name[:-2] + "_L"]]
            out[k] = pulls(mirrored)
        else:  # pragma: no cover - the table covers all 55 names (tested)
            raise KeyError(f"no procedural shape for expression '{name}'")
    return out


def shape_deltas(vertices: np.ndarray) -> np.ndarray:
    """[4,N,3] identity shape basis (a unit coefficient is a typical 1-sigma change): neck girth,
    head size, jaw width, face depth.  Joints do not move with shape, as in the release."""
    y = vertices[:, 1]
    zc, _, _ = _profile(np.minimum(y, Y_CAP))
    axis = np.stack([np.zeros_like(y), y, zc], axis=1)
    neck = 1.0 / (1.0 + np.exp((y + 3.0) / 1.0))
    head = 1.0 - neck
    jaw = _jaw_mask(vertices)
    face = _front_mask(vertices) * head
    return np.stack([
        0.08 * (vertices - axis) * np.array([1.0, 0.0, 1.0]) * neck[:, None],
        0.06 * (vertices - np.array([0.0, 4.0, 1.0])) * head[:, None],
        0.10 * vertices * np.array([1.0, 0.0, 0.0]) * jaw[:, None],
        0.6 * np.array([0.0, 0.0, 1.0]) * face[:, None] ** 2,
    ])


def larynx_maps(size: int = LARYNX_MAP_SIZE) -> np.ndarray:
    """[3,H,W] larynx displacement maps (generic, prominent, low and wide), values in [0,1].

    The shape is a thyroid-cartilage-like bump: a rounded V (the laryngeal
    prominence) over a softer body, wider at the top.
    """
    row, col = np.mgrid[0:size, 0:size].astype(np.float64)
    u = col / (size - 1)
    v = 1.0 - row / (size - 1)

    def bump(v0: float, width: float, height: float, peak: float, notch: float) -> np.ndarray:
        dv = (v - v0) / height
        du = (u - 0.5) / (width * (1.0 + 0.35 * np.clip(dv, -1, 1)))  # wider towards the top: a V
        body = np.exp(-0.5 * (du**2 + dv**2) ** 1.6)
        prominence = np.exp(-0.5 * ((u - 0.5) / (0.35 * width)) ** 2
                            - 0.5 * ((v - v0 - 0.3 * height) / (0.6 * height)) ** 2)
        image = peak * (0.75 * body + 0.25 * prominence)
        image -= notch * np.exp(-0.5 * ((u - 0.5) / (0.12 * width)) ** 2
                                - 0.5 * ((v - v0 - height) / (0.25 * height)) ** 2)
        # Compact support as the release's map, continuous at its edge.
        return np.clip((image - 0.02 * peak) / 0.98, 0.0, 1.0)

    return np.stack([
        bump(LARYNX_V, 0.045, 0.055, 0.88, 0.08),
        bump(LARYNX_V + 0.005, 0.04, 0.05, 1.0, 0.15),
        bump(LARYNX_V - 0.015, 0.06, 0.065, 0.7, 0.02),
    ]).astype(np.float32)


@lru_cache(maxsize=1)
def _cached_rig() -> RigData:
    vertices, faces, vertex_uv, uv_coords, faces_uv = body_surface()
    parents, local = cervical_chain()
    weights = skinning_weights(vertices, _joint_origins(local))
    return RigData(
        template=vertices.astype(np.float32),
        faces=faces.astype(np.int32),
        vertex_uv=vertex_uv.astype(np.float32),
        joint_names=np.array(JOINT_NAMES),
        parents=parents.astype(np.int64),
        joint_rest_local=local,
        skin_weights=weights.astype(np.float32),
        expression_names=np.array(EXPRESSION_NAMES),
        expression_deltas=expression_deltas(vertices).astype(np.float32),
        larynx_maps=larynx_maps(),
        larynx_direction=LARYNX_DIRECTION,
        uv_coords=uv_coords.astype(np.float32),
        faces_uv=faces_uv.astype(np.int32),
        shape_deltas=shape_deltas(vertices).astype(np.float32),
        source="builtin procedural rig",
    )


def build_procedural_rig() -> RigData:
    """The built-in rig (deterministic; built once per process, ~0.1 s)."""
    return _cached_rig()
