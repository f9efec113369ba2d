"""The rig posed in a capture's frame, and its Jacobian in the fit's per-frame unknowns.

Per frame the unknowns are, in this order (``FrameLayout``):

    placement rotation r [3] (axis-angle, R = exp(r) @ R_ref), translation t [3] (cm),
    theta[1:] [J-1,3] (bone frames, axis-angle; the root c7t1 is held at zero, its rotation is the placement),
    psi [E], tau [1]

and the posed vertex is ``q_n = sum_j w_nj C_j [x_n; 1]`` with ``C_j = [R | t] o A_j(theta)`` (the placement
folded into every bone's rest-to-posed transform; the skin weights sum to 1) and the rest shape
``x = T + offset + B_E psi + B_P(theta) + L(eta, tau)``.  This is the rig's linear blend skinning
(``models.rig.skinning.pose_vertices``) with the placement on top.

The Jacobian uses the structure instead of differentiating the whole mesh: the [J,12] transforms are
differentiated in (r, t, theta) by central differences (a few hundred numbers), blended by the skin weights
in one product and applied to ``[x_n; 1]``; psi, tau and eta enter the rest shape linearly (tau through the
larynx map, differentiated by a jvp), so their columns are the blended 3x3 applied to the basis.  The
pose correctives' dependence on theta (none in the release) is left out of the Jacobian (the residual keeps
them).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch

from models.rig import HeadNeckModel
from models.rig.skinning import forward_kinematics, larynx_scalar, pose_features, skinning_transforms


@dataclass(frozen=True)
class FrameLayout:
    """Slices of one frame's unknowns (see the module docstring)."""

    num_joints: int
    num_expressions: int

    @property
    def rotation(self) -> slice:
        return slice(0, 3)

    @property
    def translation(self) -> slice:
        return slice(3, 6)

    @property
    def theta(self) -> slice:
        return slice(6, 6 + 3 * (self.num_joints - 1))

    @property
    def rigid(self) -> slice:
        """placement and theta: the unknowns of the transforms."""
        return slice(0, self.theta.stop)

    @property
    def psi(self) -> slice:
        return slice(self.theta.stop, self.theta.stop + self.num_expressions)

    @property
    def tau(self) -> int:
        return self.psi.stop

    @property
    def size(self) -> int:
        return self.tau + 1


@dataclass
class Skinned:
    """A batch of B frames posed at ``vertices`` [n] (all when None), kept for the gradient and the Hessian of
    the same linearisation: the skin weights [n,J], the rest shape x [B,n,3], the transforms C [B,J,3,4]
    (placement included), their derivatives [B,J,3,4,R], per vertex their blend [B,n,3,4] (L | t) and the
    posed vertices q = L x + t [B,n,3]."""

    vertices: torch.Tensor | None
    weights: torch.Tensor
    rest: torch.Tensor
    transforms: torch.Tensor
    derivatives: torch.Tensor
    blended: torch.Tensor
    q: torch.Tensor


def rodrigues(v: torch.Tensor) -> torch.Tensor:
    """Axis-angle [...,3] -> rotation [...,3,3], smooth at zero (Taylor branch) for forward-mode autograd."""
    angle2 = (v * v).sum(-1)[..., None, None]
    small = angle2 < 1e-8
    angle = angle2.clamp_min(1e-8).sqrt()
    s = torch.where(small, 1 - angle2 / 6, torch.sin(angle) / angle)
    c = torch.where(small, 0.5 - angle2 / 24, (1 - torch.cos(angle)) / angle2.clamp_min(1e-8))
    zero = torch.zeros_like(v[..., 0])
    k = torch.stack([zero, -v[..., 2], v[..., 1], v[..., 2], zero, -v[..., 0], -v[..., 1], v[..., 0], zero],
                    -1).reshape(*v.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=v.dtype, device=v.device)
    return eye + s * k + c * (k @ k)


class RigLinearisation:
    """The rig's buffers the fit needs, and ``pose`` / ``linearise`` of a batch of frames."""

    def __init__(self, model: HeadNeckModel):
        self.model = model
        self.layout = FrameLayout(model.num_joints, model.num_expressions)
        self.weights = model.skin_weights.float()                         # [N,J]
        self.template = model.template.float()                            # [N,3]
        self.expressions = model.expression_deltas.float().contiguous()   # [E,N,3]
        self.expressions_by_vertex = self.expressions.permute(1, 2, 0).contiguous()  # [N,3,E]
        e = model.num_expressions + model.num_shapes
        self.correctives = (model.shape_basis[e: e + model.num_pose_features].transpose(1, 2).float()
                            if model.num_pose_features else None)          # [P,N,3]
        self.parents = list(model.parents)
        joints = self.weights.shape[1]
        pairs = self.weights[:, :, None] * self.weights[:, None, :]
        self.weight_pairs = pairs.reshape(-1, joints * joints)             # [N,J*J]: w_j w_k per vertex

    def transforms(self, rigid: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
        """rigid [B, 6 + 3(J-1)] (r, t, theta[1:]), reference [B,3,3] -> C [B,J,3,4]."""
        batch = rigid.shape[0]
        theta = torch.cat([rigid.new_zeros(batch, 1, 3), rigid[:, 6:].reshape(batch, -1, 3)], dim=1)
        world = forward_kinematics(rodrigues(theta), self.model.rest_local.to(rigid.dtype), self.parents)
        bones = skinning_transforms(world, self.model.rest_world_inverse.to(rigid.dtype))  # [B,J,3,4]
        rotation = rodrigues(rigid[:, 0:3]) @ reference                    # [B,3,3]
        linear = rotation[:, None] @ bones[..., :3]
        shift = (rotation[:, None] @ bones[..., 3:])[..., 0] + rigid[:, None, 3:6]
        return torch.cat([linear, shift[..., None]], dim=-1)

    def transform_derivatives(self, rigid: torch.Tensor, reference: torch.Tensor) -> torch.Tensor:
        """dC/d(r, t, theta) [B,J,3,4,R] by central differences in float64 (one batched call of a few hundred
        numbers per frame; forward-mode autograd through the kinematic chain costs ten times more)."""
        batch, size = rigid.shape
        h = 1e-5
        steps = torch.cat([torch.eye(size, dtype=torch.float64), -torch.eye(size, dtype=torch.float64)]) * h
        moved = (rigid.double()[:, None] + steps[None]).reshape(-1, size)
        ref = reference.double()[:, None].expand(batch, 2 * size, 3, 3).reshape(-1, 3, 3)
        out = self.transforms(moved, ref).reshape(batch, 2, size, -1, 3, 4)
        return ((out[:, 0] - out[:, 1]) / (2 * h)).permute(0, 2, 3, 4, 1).float()

    def rest(self, theta_rest: torch.Tensor, psi: torch.Tensor, tau: torch.Tensor, eta: torch.Tensor,
             offset: torch.Tensor | None, vertices: torch.Tensor | None = None) -> torch.Tensor:
        """The rest shape x [B,n,3] at ``vertices`` [n] (all when None)."""
        expressions = self.expressions if vertices is None else self.expressions[:, vertices]
        template = self.template if vertices is None else self.template[vertices]
        x = template + torch.einsum("be,enc->bnc", psi, expressions)
        if offset is not None:
            x = x + (offset if vertices is None else offset[vertices])
        if self.correctives is not None:
            batch = theta_rest.shape[0]
            theta = torch.cat([theta_rest.new_zeros(batch, 1, 3), theta_rest], dim=1)
            correctives = self.correctives if vertices is None else self.correctives[:, vertices]
            x = x + torch.einsum("bp,pnc->bnc", pose_features(rodrigues(theta)), correctives)
        scalar, _ = self._larynx(tau)
        return self._scatter_larynx(x, eta[:, None, None] * scalar[..., None] * self.model.larynx_direction,
                                    vertices)

    def _larynx(self, tau: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The larynx map at its vertices [B,M] and its derivative in tau [B,M] (central difference)."""
        m = self.model
        weights = tau.new_zeros(len(tau), m.num_larynx_maps)
        weights[:, 0] = 1.0

        h = 1e-4  # a fortieth of a map row: the bilinear map is linear in between (grid_sample has no forward AD)
        sampled = larynx_scalar(torch.cat([tau, tau + h, tau - h]), m.larynx_maps, weights.repeat(3, 1),
                                m.larynx_grid).reshape(3, len(tau), -1)
        return sampled[0], (sampled[1] - sampled[2]) / (2 * h)

    def _scatter_larynx(self, x: torch.Tensor, values: torch.Tensor, vertices: torch.Tensor | None) -> torch.Tensor:
        """x [B,n,3] + values [B,M,3] at the larynx vertices that are among ``vertices``."""
        if vertices is None:
            return x.index_add(1, self.model.larynx_vertices, values)
        position = torch.full((self.model.num_vertices,), -1, dtype=torch.long)
        position[vertices] = torch.arange(len(vertices))
        where = position[self.model.larynx_vertices]
        keep = where >= 0
        return x.index_add(1, where[keep], values[:, keep])

    def pose(self, rigid, psi, tau, eta, reference, offset=None, vertices=None) -> torch.Tensor:
        """Posed vertices in the capture's frame [B,n,3]."""
        with torch.no_grad():
            weights = self.weights if vertices is None else self.weights[vertices]
            x = self.rest(rigid[:, 6:].reshape(len(rigid), -1, 3), psi, tau, eta, offset, vertices)
            return self._posed(self._blend(weights, self.transforms(rigid, reference)), x)

    @staticmethod
    def _blend(weights: torch.Tensor, transforms: torch.Tensor) -> torch.Tensor:
        """Per vertex the skin-weighted transform [B,n,3,4] for weights [n,J], transforms [B,J,3,4]: one
        [n,J] x [J,12B] product."""
        batch, joints = transforms.shape[:2]
        flat = transforms.permute(1, 0, 2, 3).reshape(joints, batch * 12)
        return (weights @ flat).reshape(-1, batch, 3, 4).permute(1, 0, 2, 3)

    @staticmethod
    def _posed(blended: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """q = L x + t [B,n,3] for blended [B,n,3,4] and rest positions x [B,n,3] (no per-vertex products)."""
        q = blended[..., 3] + blended[..., 0] * x[..., 0, None]
        q.addcmul_(blended[..., 1], x[..., 1, None])
        return q.addcmul_(blended[..., 2], x[..., 2, None])

    def skin(self, rigid, psi, tau, eta, reference, offset=None, vertices=None) -> Skinned:
        """The frames posed at ``vertices`` with what their gradient and Hessian reuse (``Skinned``)."""
        derivatives = self.transform_derivatives(rigid, reference)
        with torch.no_grad():
            transforms = self.transforms(rigid, reference)
            weights = self.weights if vertices is None else self.weights[vertices]
            x = self.rest(rigid[:, 6:].reshape(len(rigid), -1, 3), psi, tau, eta, offset, vertices)
            blended = self._blend(weights, transforms)
            return Skinned(vertices, weights, x, transforms, derivatives, blended, self._posed(blended, x))

    @staticmethod
    def pull_back(skinned: Skinned, vectors: torch.Tensor) -> torch.Tensor:
        """L^T v [B,n,3] for per-vertex vectors v [B,n,3], L the blended 3x3 of the transforms (placement
        included)."""
        linear = skinned.blended
        back = linear[..., 0, :3] * vectors[..., 0, None]
        back.addcmul_(linear[..., 1, :3], vectors[..., 1, None])
        return back.addcmul_(linear[..., 2, :3], vectors[..., 2, None])

    def mean_metric(self, skinned: Skinned, weights: torch.Tensor) -> torch.Tensor:
        """mean over the frames of weights [B,n] times L^T L [n,3,3] (psi's rest-space information on meshes):
        L^T L = sum_jk w_j w_k A_j^T A_k, one [n,J*J] x [J*J, 9B] product."""
        batch, joints = skinned.transforms.shape[:2]
        a = skinned.transforms[..., :3]
        pairs = torch.einsum("bjrc,bkrd->jkbcd", a, a).reshape(joints * joints, batch * 9)
        products = self.weight_pairs if skinned.vertices is None else self.weight_pairs[skinned.vertices]
        metric = (products @ pairs).reshape(-1, batch, 9)                                      # [n,B,9]
        return (metric * weights.T[..., None]).mean(1).reshape(-1, 3, 3)

    def _features(self, rigid, psi, tau, eta, offset, vertices):
        """The skin weights [n,J] of ``vertices`` and per vertex its weights times [x; 1] for the rest
        positions x: [B,n,4J], ordered (joint, column), so that the transforms and their derivatives are one
        product each."""
        batch = rigid.shape[0]
        x = self.rest(rigid[:, 6:].reshape(batch, -1, 3), psi, tau, eta, offset, vertices)
        weights = self.weights if vertices is None else self.weights[vertices]
        n, joints = weights.shape
        features = weights[None, :, :, None] * torch.cat([x, x.new_ones(batch, n, 1)], -1)[:, :, None]
        return weights, features.reshape(batch, n, 4 * joints)

    def gradient(self, rigid, psi, tau, eta, reference, rho, offset=None, vertices=None,
                 skinned: Skinned | None = None):
        """J^T rho [B,P] and dq/deta . rho [B] for per-vertex vectors rho [B,n,3], and the ``Skinned`` frames
        (``skinned`` when given: the same frames posed at the same vertices), without the Jacobian:
        the rigid part through the skin-weighted [x; 1] rho^T (the [n,4J] features of ``linearise``), psi
        through the expressions pulled back by the blended 3x3s, tau and eta at the larynx vertices."""
        if skinned is None:
            skinned = self.skin(rigid, psi, tau, eta, reference, offset, vertices)
        batch = rigid.shape[0]
        layout = self.layout
        with torch.no_grad():
            n, joints = skinned.weights.shape
            # sum_n w_nj [x_n; 1] rho_n^T per joint: [J,n] x [n, 12B], ordered (joint, column), row.
            x = skinned.rest.permute(1, 0, 2)                               # [n,B,3]
            outer = torch.cat([x, x.new_ones(n, batch, 1)], -1)[..., :, None] * rho.permute(1, 0, 2)[..., None, :]
            projected = (skinned.weights.T @ outer.reshape(n, -1)).reshape(joints, batch, 4, 3)
            projected = projected.permute(1, 0, 2, 3).reshape(batch, 4 * joints, 3)
            columns = skinned.derivatives.permute(0, 1, 3, 2, 4).reshape(batch, 4 * joints, 3, -1)
            out = rho.new_zeros(batch, layout.size)
            out[:, layout.rigid] = torch.einsum("bkr,bkrp->bp", projected, columns)
            back = self.pull_back(skinned, rho)                             # [B,n,3] in rest space
            expressions = self.expressions_by_vertex if vertices is None else self.expressions_by_vertex[vertices]
            out[:, layout.psi] = back.reshape(batch, -1) @ expressions.reshape(-1, layout.num_expressions)
            scalar, slope = self._larynx(tau)
            at_larynx = self._gather_larynx(back, vertices) @ self.model.larynx_direction   # [B,M]
            out[:, layout.tau] = (eta[:, None] * slope * at_larynx).sum(1)
            return out, (scalar * at_larynx).sum(1), skinned

    def expression_gram(self, information: torch.Tensor, vertices=None) -> torch.Tensor:
        """sum_n E_n^T A_n E_n [E,E] for rest-space information matrices A [n,3,3] (psi's Hessian block)."""
        expressions = self.expressions_by_vertex if vertices is None else self.expressions_by_vertex[vertices]
        weighted = sum(information[:, :, d, None] * expressions[:, None, d] for d in range(3))   # [n,3,E]
        return weighted.reshape(-1, weighted.shape[-1]).T @ expressions.reshape(-1, weighted.shape[-1])

    def _gather_larynx(self, values: torch.Tensor, vertices: torch.Tensor | None) -> torch.Tensor:
        """values [B,n,3] at ``vertices`` -> [B,M,3] at the larynx vertices (zero where not among them)."""
        if vertices is None:
            return values[:, self.model.larynx_vertices]
        position = torch.full((self.model.num_vertices,), -1, dtype=torch.long)
        position[vertices] = torch.arange(len(vertices))
        where = position[self.model.larynx_vertices]
        out = values.new_zeros(values.shape[0], len(where), 3)
        keep = where >= 0
        out[:, keep] = values[:, where[keep]]
        return out

    def blended_linear(self, rigid, reference, vertices=None) -> torch.Tensor:
        """Per vertex the blended 3x3 of the transforms (placement included) [B,n,3,3]."""
        with torch.no_grad():
            weights = self.weights if vertices is None else self.weights[vertices]
            return torch.einsum("nj,bjrc->bnrc", weights, self.transforms(rigid, reference)[..., :3])

    def linearise(self, rigid, psi, tau, eta, reference, offset=None, vertices=None, derivatives=None):
        """Posed vertices q [B,n,3] and the Jacobian [B,n,3,P] in the frame's unknowns (``FrameLayout``),
        plus dq/deta [B,n,3] and the blended 3x3 [B,n,3,3] (for the shape offset); ``derivatives``: the
        transforms' derivatives when already known (``Skinned``)."""
        batch = rigid.shape[0]
        layout = self.layout
        jac_c = self.transform_derivatives(rigid, reference) if derivatives is None else derivatives
        with torch.no_grad():
            weights, features = self._features(rigid, psi, tau, eta, offset, vertices)
            n, joints = weights.shape
            transforms = self.transforms(rigid, reference)                     # [B,J,3,4]
            q = features @ transforms.transpose(2, 3).reshape(batch, 4 * joints, 3)
            jac = q.new_empty(batch, n, 3, layout.size)
            rigid_columns = jac_c.permute(0, 1, 3, 2, 4).reshape(batch, 4 * joints, -1)  # [B,4J,3R]
            jac[..., layout.rigid] = (features @ rigid_columns).reshape(batch, n, 3, -1)
            linear = torch.einsum("nj,bjrc->bnrc", weights, transforms[..., :3])  # [B,n,3,3]
            expressions = self.expressions_by_vertex if vertices is None else self.expressions_by_vertex[vertices]
            for r in range(3):
                column = linear[:, :, r, 0, None] * expressions[:, 0]
                column.addcmul_(linear[:, :, r, 1, None], expressions[:, 1])
                column.addcmul_(linear[:, :, r, 2, None], expressions[:, 2])
                jac[:, :, r, layout.psi] = column
            scalar, slope = self._larynx(tau)
            direction = self.model.larynx_direction
            zero = q.new_zeros(batch, n, 3)
            dtau = self._scatter_larynx(zero, (eta[:, None] * slope)[..., None] * direction, vertices)
            jac[..., layout.tau] = (linear @ dtau[..., None])[..., 0]
            deta = self._scatter_larynx(zero, scalar[..., None] * direction, vertices)
            deta = (linear @ deta[..., None])[..., 0]
        return q, jac, deta, linear
