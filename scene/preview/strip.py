"""The strip under a preview render: the clip's tau and summed cervical angles with a cursor at the frame,
and bars of the joints' angles at the frame.
"""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

from base.rotations import axis_angle_to_euler
from data.params import AnimationParams
from models.rig import HeadNeckModel

ANGLE_COLOURS_BGR = ((80, 80, 240), (90, 200, 90), (240, 150, 60))   # flexion, rotation, bend
TAU_COLOUR_BGR = (60, 220, 240)
BAR_RANGE_DEG = 10.0           # a joint bar at full height
STRIP_TOP, STRIP_BOTTOM = 13, 28   # pixels above and below the strip's plots (labels, two text lines)


def anatomical_degrees(rig: HeadNeckModel, theta: np.ndarray) -> np.ndarray:
    """Per-joint (flexion, axial rotation, lateral bend) [T,J,3] degrees in the anatomical frames."""
    with torch.no_grad():
        euler = axis_angle_to_euler(rig.to_anatomical(torch.as_tensor(theta, dtype=torch.float64)))
    return np.degrees(euler.numpy())


@dataclass
class Strip:
    """The strip under a render: ``base`` [h,w,3] BGR with the whole clip's curves, drawn once; ``draw(i)``
    adds the cursor, the frame's values and the joint bars."""

    base: np.ndarray
    time: np.ndarray
    tau: np.ndarray
    angles: np.ndarray          # [T,J,3] degrees
    plot_width: int
    joint_names: list

    def column(self, frame: int) -> int:
        span = max(float(self.time[-1] - self.time[0]), 1e-9)
        return int(round((self.time[frame] - self.time[0]) / span * (self.plot_width - 1)))

    def draw(self, frame: int) -> np.ndarray:
        image = self.base.copy()
        height, width = image.shape[:2]
        x = self.column(frame)
        cv2.line(image, (x, 0), (x, height - 1), (255, 255, 255), 1)
        scale = height / 90.0
        total = self.angles[frame].sum(0)
        font = cv2.FONT_HERSHEY_SIMPLEX
        cv2.putText(image, f"t {self.time[frame]:.2f} s", (3, height - 16), font, 0.32 * scale, (235, 235, 235), 1,
                    cv2.LINE_AA)
        cv2.putText(image, f"tau {self.tau[frame]:+.4f}", (int(width * 0.33), height - 16), font, 0.32 * scale,
                    TAU_COLOUR_BGR, 1, cv2.LINE_AA)
        for k, (name, value) in enumerate(zip(("flex", "rot", "bend"), total)):
            cv2.putText(image, f"{name} {value:+.1f}", (3 + int(width * 0.27 * k), height - 4), font, 0.32 * scale,
                        ANGLE_COLOURS_BGR[k], 1, cv2.LINE_AA)
        cv2.putText(image, "deg", (3 + int(width * 0.81), height - 4), font, 0.32 * scale, (235, 235, 235), 1,
                    cv2.LINE_AA)
        # Joint bars: per joint three bars (flexion, rotation, bend) about a zero line, +-BAR_RANGE_DEG.
        left = self.plot_width + 4
        slot = max((width - left - 2) // len(self.joint_names), 3)
        zero = (STRIP_TOP + height - STRIP_BOTTOM) // 2
        half = (height - STRIP_BOTTOM - STRIP_TOP) // 2
        cv2.line(image, (left, zero), (width - 2, zero), (110, 110, 110), 1)
        bar = max(slot // 4, 1)
        for j in range(len(self.joint_names)):
            for k in range(3):
                value = float(np.clip(self.angles[frame, j, k] / BAR_RANGE_DEG, -1.0, 1.0))
                x0 = left + j * slot + k * bar
                y1 = int(round(zero - value * half))
                cv2.rectangle(image, (x0, min(zero, y1)), (x0 + bar - 1, max(zero, y1)), ANGLE_COLOURS_BGR[k], -1)
        return image


def make_strip(rig: HeadNeckModel, params: AnimationParams, width: int, height: int) -> Strip:
    """The strip of a clip ``width`` x ``height`` pixels: 70 % curves over the whole clip (tau scaled to
    its range, the summed angles to +-their largest magnitude), 30 % joint bars."""
    angles = anatomical_degrees(rig, params.theta)
    tau = np.asarray(params.tau, np.float64)
    base = np.full((height, width, 3), 18, np.uint8)
    plot_width = int(width * 0.7)
    top, bottom = STRIP_TOP, height - STRIP_BOTTOM
    columns = np.linspace(0, plot_width - 1, len(params)) if len(params) > 1 else np.zeros(1)
    if len(params) > 1:
        span = max(float(params.time[-1] - params.time[0]), 1e-9)
        columns = (params.time - params.time[0]) / span * (plot_width - 1)

    def curve(values: np.ndarray, limit: float, colour) -> None:
        mid = (top + bottom) / 2
        rows = mid - np.clip(values / max(limit, 1e-12), -1, 1) * (bottom - top) / 2
        points = np.stack([columns, rows], 1).round().astype(np.int32)
        cv2.polylines(base, [points], False, colour, 1, cv2.LINE_AA)

    cv2.line(base, (0, (top + bottom) // 2), (plot_width - 1, (top + bottom) // 2), (70, 70, 70), 1)
    totals = angles.sum(1)
    limit = float(np.abs(totals).max())
    for k in range(3):
        curve(totals[:, k], limit, ANGLE_COLOURS_BGR[k])
    centre = (tau.max() + tau.min()) / 2
    curve(tau - centre, float(np.abs(tau - centre).max()), TAU_COLOUR_BGR)
    scale = height / 90.0
    cv2.putText(base, f"tau {tau.min():+.3f}..{tau.max():+.3f}", (3, 10), cv2.FONT_HERSHEY_SIMPLEX,
                0.3 * scale, TAU_COLOUR_BGR, 1, cv2.LINE_AA)
    cv2.putText(base, f"angles +-{limit:.0f} deg", (int(plot_width * 0.55), 10), cv2.FONT_HERSHEY_SIMPLEX,
                0.3 * scale, (200, 200, 200), 1, cv2.LINE_AA)
    return Strip(base, np.asarray(params.time), tau, angles, plot_width, list(params.joint_names))
