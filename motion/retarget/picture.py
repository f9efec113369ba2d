"""The reference poses picture: four head poses on the source and the target, rendered side by side."""
from __future__ import annotations

import os

import numpy as np
import torch

from base.plots import figure, save_figure
from base.rotations import euler_to_axis_angle
from data.joint_limits import range_of_motion_shares
from data.params import AnimationParams
from models.rig import HeadNeckModel
from motion.retarget.posing import pose
from motion.retarget.transfer import character_limits, retarget_theta
from scene.preview import framing_camera, shade
from scene.render import outward_faces, render_normals

# Head angles of the four reference poses (degrees, anatomical Euler axis), spread over the joints by
# their human ranges of motion in that direction: extension -40 (flexion axis), side-bend 30 (lateral, to
# the right), flexion 40, twist 50 (axial, to the left); each inside every joint's range (the chain's:
# extension 77.4, lateral 61, flexion 60.5, axial 77 degrees).
REFERENCE_POSES = {"extension": (0, -40.0), "side-bend": (2, 30.0), "flexion": (0, 40.0), "twist": (1, 50.0)}
POSE_VIEWS = {"extension": "side", "side-bend": "front", "flexion": "side", "twist": "three_quarter"}


def reference_theta(rig: HeadNeckModel, name: str) -> torch.Tensor:
    """theta [1,J,3] (``rig``'s bone frames) of a reference pose: the head angle of ``REFERENCE_POSES[name]``
    spread over the joints by their human range-of-motion shares in that direction
    (``data.joint_limits.range_of_motion_shares``, anatomical frames)."""
    axis, degrees = REFERENCE_POSES[name]
    positive, negative = range_of_motion_shares()
    share = (positive if degrees > 0 else negative)[:, axis].double()
    euler = torch.zeros(1, rig.num_joints, 3, dtype=torch.float64)
    euler[0, :, axis] = np.radians(degrees) * share
    return rig.from_anatomical(euler_to_axis_angle(euler)).float()


def _still(rig: HeadNeckModel, theta: torch.Tensor, view: str, size: int, skinning: str) -> np.ndarray:
    params = AnimationParams(time=np.zeros(1), fps=1.0, psi=np.zeros((1, len(rig.expression_names))),
                             tau=np.zeros(1), eta=np.ones(1), theta=theta.numpy(),
                             head_rotation=np.eye(3)[None], joint_names=rig.joint_names,
                             expression_names=rig.expression_names)
    camera = framing_camera(rig, params, view, size)
    vertices = next(pose(rig, params, skinning))[1]
    render = render_normals(vertices, outward_faces(rig.template, rig.faces.numpy()), camera)
    return shade(render.normals.numpy(), render.mask.numpy())[0][..., ::-1]   # BGR -> RGB


def pose_picture(path: str | os.PathLike, source: HeadNeckModel, target: HeadNeckModel,
                 gains: np.ndarray | None = None, size: int = 320, skinning: str = "lbs",
                 names: tuple[str, ...] = ("source", "target")) -> None:
    """The source and the target in the four reference poses (rows: characters; columns: poses), rendered
    by ``scene.render`` (shaded as ``scene.preview``), the target's theta retargeted from the source's with
    ``gains`` and clamped to its limits when gains are given; saved atomically to ``path``."""
    fig, axes = figure(nrows=2, ncols=len(REFERENCE_POSES), figsize=(3.2 * len(REFERENCE_POSES), 6.8))
    limits = character_limits(target) if gains is not None else None
    for column, pose_name in enumerate(REFERENCE_POSES):
        theta = reference_theta(source, pose_name)
        with torch.no_grad():
            theta_target = retarget_theta(theta, source, target, gains, limits)
        for row, (rig, value) in enumerate(((source, theta), (target, theta_target))):
            ax = axes[row, column]
            ax.imshow(_still(rig, value, POSE_VIEWS[pose_name], size, skinning))
            ax.set_xticks([])
            ax.set_yticks([])
            if row == 0:
                ax.set_title(f"{pose_name} ({POSE_VIEWS[pose_name].replace('_', ' ')} view)")
            if column == 0:
                ax.set_ylabel(names[row])
    save_figure(fig, path)
