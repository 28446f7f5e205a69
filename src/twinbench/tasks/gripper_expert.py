"""What the gripper experts (rope routing, toy packing) share: the grasp orientation, a rate-limited
waypoint (held deformable objects move without jerks: the grasp is friction only) and a plan runner.

An expert plans once, from the first `environment_state` of an episode, a list of `Leg`s (go to a pose
with a gripper command until the end-effector is within `tol` of it, or for a number of steps), and
`GripperExpert.select_action` walks through it. Legs are positions of the tool point (`tcp`); the expert
commands the twin's end-effector frame (the flange in the reference cells), `tool_offset` away
(`tasks.base.tool_offset`, which the tasks' `make_expert` reads from the env's twin).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinbench.errors import PolicyError
from twinbench.transforms import quat_multiply, quat_to_matrix

DOWN = np.array([0.0, 1.0, 0.0, 0.0])  # tcp z down, tcp x = world x (wxyz)
TCP_ABOVE_TIPS = 0.015  # the built-in gripper's tcp sits 15 mm above its fingertips


def grasp_yaw(direction_xy) -> float:
    """The yaw of tcp x along `direction_xy`, folded into [-pi/2, pi/2) since the fingers are symmetric."""
    yaw = float(np.arctan2(direction_xy[1], direction_xy[0]))
    return (yaw + np.pi / 2) % np.pi - np.pi / 2


def down_quat(yaw: float) -> np.ndarray:
    """Gripper pointing down with tcp x at `yaw` (rad, about world z; not folded)."""
    return quat_multiply(np.array([np.cos(yaw / 2), 0.0, 0.0, np.sin(yaw / 2)]), DOWN)


def grasp_quat(direction_xy) -> np.ndarray:
    """Gripper pointing down with tcp x along `direction_xy` (the fingers close across it), yaw folded
    (`grasp_yaw`)."""
    return down_quat(grasp_yaw(direction_xy))


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


@dataclass(frozen=True)
class Leg:
    """Command (`position`, `quat`, `gripper`) until the end-effector is within `tol` of `position` (or,
    with `tol` None, for `steps` steps); give up after `steps` steps. `slow`: the rate-limited waypoint
    (while holding). A last leg with `steps` None lasts for the rest of the episode."""

    name: str
    position: np.ndarray
    quat: np.ndarray
    gripper: float
    tol: float | None = None
    steps: int | None = None
    slow: bool = False

    def done(self, ee: np.ndarray, t: int) -> bool:
        if self.tol is not None and np.linalg.norm(ee - self.position) < self.tol:
            return True
        return self.steps is not None and t > self.steps


class GripperExpert:
    """Walks a plan of Legs made by `plan(environment_state)` (a subclass's). `phase` names the leg.
    `tool_offset`: the tool point in the end-effector frame (zeros: the end-effector is the tool point)."""

    uses_environment_state = True

    def __init__(self, holding_speed: float, tool_offset=(0.0, 0.0, 0.0)):
        self.holding_speed = holding_speed
        self.tool_offset = np.asarray(tool_offset, dtype=np.float64)
        self.reset()

    def reset(self) -> None:
        self._plan: list[Leg] | None = None
        self._leg, self._t = 0, 0
        self._wp = Waypoint()

    @property
    def phase(self) -> str:
        return "plan" if self._plan is None else self._plan[self._leg].name

    def plan(self, state: np.ndarray) -> list[Leg]:
        raise NotImplementedError

    def select_action(self, obs) -> np.ndarray:
        if "environment_state" not in obs:
            raise PolicyError(
                f"{type(self).__name__} needs obs['environment_state'] (make the env with "
                "environment_state=True, or let the evaluation runner add it)"
            )
        if self._plan is None:
            self._plan = self.plan(np.asarray(obs["environment_state"], dtype=np.float64))
        ee = np.asarray(obs["agent_pos"], dtype=np.float64)
        tool = ee[:3] + quat_to_matrix(ee[3:7]) @ self.tool_offset
        self._t += 1
        while self._leg < len(self._plan) - 1 and self._plan[self._leg].done(tool, self._t):
            self._leg, self._t = self._leg + 1, 0
        leg = self._plan[self._leg]
        target = self._wp.toward(leg.position, self.holding_speed, leg.slow)
        target = target - quat_to_matrix(np.asarray(leg.quat, np.float64)) @ self.tool_offset
        return np.r_[target, leg.quat, leg.gripper].astype(np.float32)
