"""What the gripper experts (rope routing, toy packing) share: the grasp orientation and a rate-limited
waypoint, so that held deformable objects move without jerks (the grasp is friction only)."""

from __future__ import annotations

import numpy as np

from twinbench.transforms import quat_multiply

DOWN = np.array([0.0, 1.0, 0.0, 0.0])  # tcp z down, tcp x = world x (wxyz)
TCP_ABOVE_TIPS = 0.015  # the built-in gripper's tcp sits 15 mm above its fingertips


def grasp_quat(direction_xy) -> np.ndarray:
    """Gripper pointing down with tcp x along `direction_xy` (the fingers close across it); yaw folded
    into [-pi/2, pi/2] since the fingers are symmetric."""
    yaw = float(np.arctan2(direction_xy[1], direction_xy[0]))
    yaw = (yaw + np.pi / 2) % np.pi - np.pi / 2
    return quat_multiply(np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]), DOWN)


class Waypoint:
    """A commanded position that moves towards each new target by at most `speed` metres per step
    (free jumps when `limited` is False). The controller's velocity mimic lags behind it."""

    def __init__(self):
        self.position: np.ndarray | None = None

    def reset(self) -> None:
        self.position = None

    def toward(self, target, speed: float, limited: bool) -> np.ndarray:
        target = np.asarray(target, dtype=np.float64)
        if self.position is None or not limited:
            self.position = target.copy()
        else:
            step = target - self.position
            dist = float(np.linalg.norm(step))
            self.position = target.copy() if dist <= speed else self.position + step * (speed / dist)
        return self.position
