"""The rig's forward pass as pure, batched steps (as smplx's ``lbs.py``), and ``pose_vertices``, the whole
forward composed from them in plain torch: the reference the threaded engine (``models.rig.engine``) equals.

    G = skin(T + B_E(psi) + B_S(beta) + B_P(theta) + L(eta, tau), W, G_j(theta) G_j(0)^-1)

with ``skin`` linear blend skinning or dual-quaternion skinning (Kavan et al. 2008).  Conventions of the
inputs (theta, psi, tau, eta, units and frames): ``models.rig.model``.

Layouts: vertices are ``[B,N,3]`` at the interfaces.  Inside, vertices are planar with the batch in the middle,
``[3,B,M]`` (x, y, z planes of B frames of M vertices): every GEMM writes its result in that layout and every
elementwise step runs over contiguous rows of vertices, whatever the batch size.  The shape basis is planar
too, ``[K,3,N]`` (per shape its x, y and z offsets as rows), the template its last shape (coefficient 1).
"""
from __future__ import annotations

from collections.abc import Sequence

import torch
import torch.nn.functional as F

from base.rotations import axis_angle_to_matrix, matrix_to_quaternion, quaternion_multiply

SKINNINGS = ("lbs", "dqs")

# ----------------------------------------------------------------------------- rest shape and kinematics


def blend_shapes(coefficients: torch.Tensor, basis: torch.Tensor) -> torch.Tensor:
    """Linear blendshapes in the planar layout: ``sum_k c_bk basis_k``.

    coefficients [B,K], basis [K,3,N] (per shape its x, y and z offsets as rows) -> [B,3,N].
    ``HeadNeckModel.shape_basis`` ends with the template (coefficient 1): T + B_E + B_S + B_P in one product.
    """
    return (coefficients @ basis.reshape(basis.shape[0], -1)).reshape(coefficients.shape[0], 3, -1)


def pose_features(rotations: torch.Tensor) -> torch.Tensor:
    """SMPL-style pose-corrective features: (R - I) per joint, the root's zeroed (the release's rule).

    rotations [B,J,3,3] -> features [B,J*9].
    """
    eye = torch.eye(3, dtype=rotations.dtype, device=rotations.device)
    features = rotations - eye
    features = torch.cat([torch.zeros_like(features[:, :1]), features[:, 1:]], dim=1)
    return features.reshape(rotations.shape[0], -1)


def larynx_scalar(tau: torch.Tensor, maps: torch.Tensor, map_weights: torch.Tensor,
                  grid: torch.Tensor) -> torch.Tensor:
    """Larynx displacement magnitude at vertices, the maps slid vertically by tau.

    tau [B] (UV units, + = up), maps [K,H,W], map_weights [B,K],
    grid [N,2] vertex UVs in grid_sample coordinates ((2u - 1, 2(1 - v) - 1)) -> [B,N].
    All frames sample the K maps as channels of one image (sampling is linear, so the identity
    weights apply afterwards): no per-frame copy of the maps.
    """
    shifted = grid[None].expand(tau.shape[0], -1, -1) + torch.stack([torch.zeros_like(tau), 2.0 * tau], dim=-1)[:, None]
    sampled = F.grid_sample(maps[None], shifted[None], mode="bilinear", padding_mode="border", align_corners=True)
    return torch.einsum("kbn,bk->bn", sampled[0], map_weights)


def larynx_offsets(tau: torch.Tensor, eta: torch.Tensor, maps: torch.Tensor, map_weights: torch.Tensor,
                   grid: torch.Tensor, direction: torch.Tensor) -> torch.Tensor:
    """The larynx term ``L = eta * (sum_k w_k Lc_k)(u, v + tau) * direction`` at the vertices of ``grid``.

    tau [B], eta [B], maps [K,H,W], map_weights [B,K], grid [M,2] (``larynx_scalar``), direction [3] -> [B,M,3].
    """
    return (eta[:, None] * larynx_scalar(tau, maps, map_weights, grid))[..., None] * direction


def forward_kinematics(rotations: torch.Tensor, rest_local: torch.Tensor, parents: Sequence[int]) -> torch.Tensor:
    """World transforms of the bones.  G_j = G_parent(j) @ L2P_j @ [R_j 0; 0 1].

    rotations [B,J,3,3], rest_local [J,4,4] -> [B,J,4,4]; with rest_local [J,3,3] (the rest rotations
    alone) the chain's world rotations [B,J,3,3] (what a head orientation needs: translations turn nothing).
    """
    batch, joints = rotations.shape[:2]
    if rest_local.shape[-1] == 3:
        posed_local = rest_local @ rotations
    else:
        local = rest_local[None].expand(batch, -1, -1, -1)
        posed_local = torch.cat([local[..., :3, :3] @ rotations, local[..., :3, 3:]], dim=-1)
        bottom = torch.zeros(batch, joints, 1, 4, dtype=rotations.dtype, device=rotations.device)
        bottom[..., 3] = 1.0
        posed_local = torch.cat([posed_local, bottom], dim=-2)
    world: list[torch.Tensor] = []
    for j, parent in enumerate(parents):
        world.append(posed_local[:, j] if parent < 0 else world[parent] @ posed_local[:, j])
    return torch.stack(world, dim=1)


def nearest_axis_permutation(rotation: torch.Tensor) -> torch.Tensor:
    """The signed permutation matrix (a proper rotation by quarter turns) nearest to ``rotation`` [3,3]."""
    remaining = rotation.abs().clone()
    out = torch.zeros_like(rotation)
    for _ in range(3):
        row, column = divmod(int(torch.argmax(remaining)), 3)
        out[row, column] = torch.sign(rotation[row, column])
        remaining[row, :] = -1.0
        remaining[:, column] = -1.0
    return out


def skinning_transforms(world: torch.Tensor, rest_world_inverse: torch.Tensor) -> torch.Tensor:
    """Per-bone transforms from rest to posed space: G_j(theta) @ G_j(0)^-1, top 3 rows.

    world [B,J,4,4], rest_world_inverse [J,4,4] -> [B,J,3,4].
    """
    return (world @ rest_world_inverse)[..., :3, :]


# ----------------------------------------------------------------------------- linear blend skinning


def transform_columns(transforms: torch.Tensor) -> torch.Tensor:
    """[B,J,3,4] -> [12B, J], rows ordered (column k of the 3x4, row d, frame b): ``rows @ weights.T`` gives
    every vertex's blended 3x4 as [4,3,B,M]."""
    batch, joints = transforms.shape[:2]
    return transforms.permute(3, 2, 0, 1).reshape(12 * batch, joints)


def apply_blended(blended: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """blended [4,3,B,M] (columns of per-vertex 3x4s), rest [3,B,M] -> [3,B,M]: three fused multiply-adds."""
    posed = torch.addcmul(blended[3], blended[0], rest[0:1])
    return posed.addcmul_(blended[1], rest[1:2]).addcmul_(blended[2], rest[2:3])


def linear_blend_skinning(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
    """Linear blend skinning, v'_n = sum_j w_nj (R_j v_n + t_j) (the release's, and smplx's ``lbs``).

    Args:
        vertices: [B,N,3] rest-pose vertices (cm).
        weights: [N,J] skinning weights (rows sum to 1).
        transforms: [B,J,3,4] rest-to-posed bone transforms (``skinning_transforms``).

    Returns:
        [B,N,3] posed vertices.  The 3x4s are blended per vertex with one [12B,J] x [J,N] product and applied
        with three fused multiply-adds, never a dense 4x4 per vertex (the release's formulation).
    """
    batch = transforms.shape[0]
    blended = (transform_columns(transforms) @ weights.T).reshape(4, 3, batch, -1)
    return apply_blended(blended, vertices.permute(2, 0, 1)).permute(1, 2, 0)


# ----------------------------------------------------------------------------- dual-quaternion skinning


def rigid_to_dual_quaternion(transforms: torch.Tensor) -> torch.Tensor:
    """Rigid transforms [...,3,4] ``(R | t)`` -> unit dual quaternions [...,8]: the real part ``q = quat(R)``
    (w, x, y, z; w >= 0) then the dual part ``1/2 (0, t) q`` (Hamilton product, ``base.rotations``)."""
    real = matrix_to_quaternion(transforms[..., :3, :3])
    translation = transforms[..., :3, 3]
    pure = torch.cat([torch.zeros_like(translation[..., :1]), translation], dim=-1)
    return torch.cat([real, 0.5 * quaternion_multiply(pure, real)], dim=-1)


def dual_quaternion_pivots(weights: torch.Tensor) -> torch.Tensor:
    """weights [N,J] -> [N] long: each vertex's most influential joint, the one the signs of the others'
    quaternions are aligned with before blending (Kavan et al. 2008, sec. 3.3)."""
    return weights.argmax(dim=1)


def pivot_usage(weights: torch.Tensor, pivots: torch.Tensor) -> torch.Tensor:
    """[J,J] bool: ``usage[p, j]`` when some vertex of pivot ``p`` has a non-zero weight on joint ``j``."""
    joints = weights.shape[1]
    counts = F.one_hot(pivots, joints).to(torch.float64).T @ (weights != 0).to(torch.float64)
    return counts > 0


def dual_quaternion_columns(dual_quaternions: torch.Tensor,
                             usage: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
    """Per-frame dual quaternions [B,J,8] -> ``(columns [8B,J], signed [8B,J*J] or None)``, rows ordered
    (component, frame) like ``transform_columns``.  ``signed`` holds, per pivot p (column block p), the
    quaternions with the signs that put their real parts in pivot p's hemisphere; it is None when no used
    (pivot, joint) pair needs a flip in any frame, the common case (then ``columns`` blends every vertex)."""
    batch, joints = dual_quaternions.shape[:2]
    columns = dual_quaternions.permute(2, 0, 1).reshape(8 * batch, joints)
    real = dual_quaternions[..., :4]
    flips = torch.einsum("bpc,bjc->bpj", real, real) < 0  # [B, pivot, joint]
    if not bool((flips & usage).any()):
        return columns, None
    sign = 1.0 - 2.0 * flips.to(dual_quaternions.dtype)
    signed = (sign[..., None] * dual_quaternions[:, None]).permute(3, 0, 1, 2)  # [8, B, pivot, joint]
    return columns, signed.reshape(8 * batch, joints * joints)


def blend_dual_quaternions(weights: torch.Tensor, pivots: torch.Tensor, columns: torch.Tensor,
                            signed: torch.Tensor | None) -> torch.Tensor:
    """weights [M,J], pivots [M] -> blended dual quaternions [8,B,M] (not normalised)."""
    count, joints = weights.shape
    if signed is None:
        blended = columns @ weights.T
    else:  # each vertex's weights moved to the block of its pivot: one GEMM with the signed table
        pick = F.one_hot(pivots, joints).to(weights.dtype)
        blended = signed @ (pick[:, :, None] * weights[:, None, :]).reshape(count, joints * joints).T
    return blended.reshape(8, -1, count)


def _quadratic_forms() -> torch.Tensor:
    """[12,32]: the 3x4 ``(R | t)`` of a dual quaternion ``q_r + eps q_d`` times ``|q_r|^2``, as a linear map of
    the products ``q_r[a] q_r[b]`` (entries 0-15, a-major) and ``q_d[a] q_r[b]`` (16-31); rows ordered (column k
    of the 3x4, row d) like ``transform_columns``.  R is the rotation of the unit quaternion, and
    t = 2 vec(q_d q_r*) = 2 (w_r d - d_w r + r x d)."""
    rr = lambda a, b: a * 4 + b  # noqa: E731 - index of q_r[a] q_r[b]
    dr = lambda a, b: 16 + a * 4 + b  # noqa: E731 - index of q_d[a] q_r[b]
    w, x, y, z = range(4)
    terms = {  # (row d, column k) -> [(coefficient, product index)]
        (0, 0): [(1, rr(w, w)), (1, rr(x, x)), (-1, rr(y, y)), (-1, rr(z, z))],
        (0, 1): [(2, rr(x, y)), (-2, rr(w, z))], (0, 2): [(2, rr(x, z)), (2, rr(w, y))],
        (1, 0): [(2, rr(x, y)), (2, rr(w, z))],
        (1, 1): [(1, rr(w, w)), (-1, rr(x, x)), (1, rr(y, y)), (-1, rr(z, z))],
        (1, 2): [(2, rr(y, z)), (-2, rr(w, x))],
        (2, 0): [(2, rr(x, z)), (-2, rr(w, y))], (2, 1): [(2, rr(y, z)), (2, rr(w, x))],
        (2, 2): [(1, rr(w, w)), (-1, rr(x, x)), (-1, rr(y, y)), (1, rr(z, z))],
        (0, 3): [(2, dr(x, w)), (-2, dr(w, x)), (2, dr(z, y)), (-2, dr(y, z))],
        (1, 3): [(2, dr(y, w)), (-2, dr(w, y)), (2, dr(x, z)), (-2, dr(z, x))],
        (2, 3): [(2, dr(z, w)), (-2, dr(w, z)), (2, dr(y, x)), (-2, dr(x, y))],
    }
    forms = torch.zeros(12, 32, dtype=torch.float64)
    for (d, k), entries in terms.items():
        for coefficient, index in entries:
            forms[3 * k + d, index] += coefficient
    return forms


_QUADRATIC_FORMS = _quadratic_forms()


def apply_dual_quaternions(blended: torch.Tensor, rest: torch.Tensor) -> torch.Tensor:
    """blended [8,B,M] (real w,x,y,z | dual w,x,y,z, not normalised), rest [3,B,M] -> [3,B,M].

    The rigid transform of the normalised dual quaternion, ``(R | t) = Q(q_r, q_d) / |q_r|^2`` with Q the
    quadratic forms of ``_quadratic_forms`` (the products of the components, then one small GEMM), applied
    like LBS's blended 3x4s.
    """
    real = blended[:4]
    products = (blended[:, None] * real[None]).reshape(32, -1)  # q[a] q_r[b], a-major
    forms = _QUADRATIC_FORMS.to(dtype=blended.dtype, device=blended.device)
    transform = (forms @ products).view(4, 3, *blended.shape[1:])
    return apply_blended(transform, rest) / (real * real).sum(0).clamp_min(torch.finfo(blended.dtype).tiny)


def dual_quaternion_skinning(vertices: torch.Tensor, weights: torch.Tensor, transforms: torch.Tensor,
                             pivots: torch.Tensor | None = None) -> torch.Tensor:
    """Dual-quaternion linear blending (Kavan, Collins, Zara and O'Sullivan, "Geometric skinning with
    approximate dual quaternion blending", ACM TOG 27(4), 2008), a drop-in for ``linear_blend_skinning``.

    v'_n = T(q_n) v_n with q_n = sum_j w_nj s_nj Q_j normalised by its real part's norm, Q_j the unit dual
    quaternion of bone j's rigid transform and s_nj = +-1 putting Q_j's real part in the hemisphere of the
    pivot's (``dual_quaternion_pivots``).  A twisted chain keeps its volume and girth where LBS collapses it;
    with one-hot weights it equals LBS.

    Args:
        vertices: [B,N,3] rest-pose vertices (cm).
        weights: [N,J] skinning weights (rows sum to 1).
        transforms: [B,J,3,4] rigid rest-to-posed bone transforms (``skinning_transforms``).
        pivots: [N] long, each vertex's sign-reference joint; default the joint of its largest weight.

    Returns:
        [B,N,3] posed vertices.
    """
    pivots = dual_quaternion_pivots(weights) if pivots is None else pivots
    columns, signed = dual_quaternion_columns(rigid_to_dual_quaternion(transforms), pivot_usage(weights, pivots))
    blended = blend_dual_quaternions(weights, pivots, columns, signed)
    return apply_dual_quaternions(blended, vertices.permute(2, 0, 1)).permute(1, 2, 0)


# ----------------------------------------------------------------------------- the whole forward pass


def pose_vertices(theta: torch.Tensor, shape_coefficients: torch.Tensor, tau: torch.Tensor, eta: torch.Tensor,
                  larynx_weights: torch.Tensor, *, shape_basis: torch.Tensor, rest_local: torch.Tensor,
                  parents: Sequence[int], rest_world_inverse: torch.Tensor, skin_weights: torch.Tensor,
                  larynx_maps: torch.Tensor, larynx_grid: torch.Tensor, larynx_vertices: torch.Tensor,
                  larynx_direction: torch.Tensor, skinning: str = "lbs",
                  pivots: torch.Tensor | None = None) -> torch.Tensor:
    """Posed vertices, the forward pass step by step over the whole mesh (no chunks, threads or selection).

    Args:
        theta: [B,J,3] axis-angle radians per joint in its bone frame.
        shape_coefficients: [B,E+S] expression then identity-shape weights (psi, beta).
        tau: [B] larynx slide; eta: [B] larynx size; larynx_weights: [B,K] identity weights of the maps.
        shape_basis: [E+S+P+1,3,N] expressions, shapes, pose correctives (P = 9J, or none) and the template.
        rest_local: [J,4,4] rest transforms child-to-parent; parents: J parent indices (-1 for the root).
        rest_world_inverse: [J,4,4] inverses of the rest world transforms.
        skin_weights: [N,J].  larynx_maps [K,H,W]; larynx_grid [M,2] and larynx_vertices [M] the vertices the
            larynx can move and their sampling points; larynx_direction [3].
        skinning: "lbs" or "dqs"; pivots [N] the DQS sign-reference joints (default: the heaviest weight).

    Returns:
        [B,N,3] posed vertices (cm).
    """
    batch = theta.shape[0]
    rotations = axis_angle_to_matrix(theta)  # [B,J,3,3]
    parts = [shape_coefficients]
    if shape_basis.shape[0] - shape_coefficients.shape[1] > 1:  # the rig has pose correctives
        parts.append(pose_features(rotations))
    coefficients = torch.cat([*parts, shape_coefficients.new_ones(batch, 1)], dim=1)  # [B,K]
    rest = blend_shapes(coefficients, shape_basis).transpose(1, 2)  # T + B_E + B_S + B_P  [B,N,3]
    larynx = larynx_offsets(tau, eta, larynx_maps, larynx_weights, larynx_grid, larynx_direction)  # [B,M,3]
    rest = rest.index_add(1, larynx_vertices, larynx)  # + L
    transforms = skinning_transforms(forward_kinematics(rotations, rest_local, parents), rest_world_inverse)
    if skinning == "lbs":
        return linear_blend_skinning(rest, skin_weights, transforms)
    if skinning == "dqs":
        return dual_quaternion_skinning(rest, skin_weights, transforms, pivots)
    raise ValueError(f"skinning={skinning!r}: expected one of {', '.join(SKINNINGS)}")
