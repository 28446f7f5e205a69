"""Scripted rope-routing expert: grasp the marked end, lift, carry it to the channel's axis before the
near opening, drag it along the axis just above the clip (the hanging rope trails into the channel),
lower it beyond the far opening, release, and keep clear.

It acts from `obs["environment_state"]` (see tasks.rope_routing): the marked end, a rope point 4 cm from
it (the rope's direction at the end, for the finger orientation), the rope's centroid and the clip pose.
"""

from __future__ import annotations

import numpy as np

from twinbench.policies.base import PolicyError
from twinbench.tasks.gripper_expert import TCP_ABOVE_TIPS, Waypoint, grasp_quat


class RopeExpert:
    """Phase machine over `environment_state`; see the module docstring."""

    uses_environment_state = True
    PHASES = ("approach", "descend", "close", "lift", "carry", "skim", "drag", "lower", "release", "retreat")

    def __init__(
        self,
        *,
        channel_length: float = 0.04,
        channel_depth: float = 0.03,
        grip_inset: float = 0.012,
        carry_height: float = 0.12,
        beyond: float = 0.07,
        close_steps: int = 20,
        settle_steps: int = 25,
        holding_speed: float = 0.006,
        squeeze: float = 0.92,
    ):
        self.channel_length, self.channel_depth = channel_length, channel_depth
        self.grip_inset, self.carry_height, self.beyond = grip_inset, carry_height, beyond
        self.close_steps, self.settle_steps = close_steps, settle_steps
        self.holding_speed = holding_speed
        # gripper command while holding: fingers 6.8 mm apart, pressing into the 8-10 mm rope (closing
        # fully would push particles into the finger meshes, where they stay trapped)
        self.squeeze = squeeze  # m per step while the rope is held (friction grasp: no jerks)
        self.reset()

    def reset(self) -> None:
        self.phase, self._t, self._quat, self._grip, self._goal = "approach", 0, None, None, None
        self._wp = Waypoint()

    def _next(self, phase: str) -> None:
        self.phase, self._t = phase, 0

    def select_action(self, obs) -> np.ndarray:
        if "environment_state" not in obs:
            raise PolicyError(
                "the rope expert needs obs['environment_state'] (make the env with "
                "environment_state=True, or let the evaluation runner add it)"
            )
        s = np.asarray(obs["environment_state"], dtype=np.float64)
        end, along, centroid, clip = s[0:3], s[3:6], s[6:9], s[9:12]
        ee = np.asarray(obs["agent_pos"], dtype=np.float64)[:3]
        self._t += 1
        if self._quat is None:  # fix the grasp point and orientation from the rope at rest
            direction = end[:2] - along[:2]
            direction /= max(np.linalg.norm(direction), 1e-9)
            self._quat = grasp_quat(direction)
            self._grip = np.r_[end[:2] - self.grip_inset * direction, TCP_ABOVE_TIPS + 0.002]
        if self._goal is None:  # on the channel's axis: before the near opening and beyond the far one
            axis = np.array([-np.sin(clip[2]), np.cos(clip[2])])  # clip frame y in the world
            if axis @ (clip[:2] - centroid[:2]) < 0:
                axis = -axis
            self._near = clip[:2] - axis * (self.channel_length / 2 + 0.03)
            self._goal = clip[:2] + axis * (self.channel_length / 2 + self.beyond)
        above = np.r_[self._grip[:2], 0.08]
        skim = self.channel_depth + 0.02 + TCP_ABOVE_TIPS  # fingertips 2 cm above the clip's walls
        near_high, near_low = np.r_[self._near, self.carry_height], np.r_[self._near, skim]
        goal_skim = np.r_[self._goal, skim]
        goal_low = np.r_[self._goal, self.channel_depth * 0.5 + TCP_ABOVE_TIPS]
        target, g = above, 0.0
        if self.phase == "approach":
            if np.linalg.norm(ee - above) < 0.01 or self._t > 60:
                self._next("descend")
        if self.phase == "descend":
            target = self._grip
            if np.linalg.norm(ee - self._grip) < 0.006 or self._t > 60:
                self._next("close")
        if self.phase == "close":
            target, g = self._grip, self.squeeze
            if self._t > self.close_steps:
                self._next("lift")
        if self.phase == "lift":
            target, g = np.r_[self._grip[:2], self.carry_height], self.squeeze
            if abs(ee[2] - self.carry_height) < 0.01 or self._t > 90:
                self._next("carry")
        if self.phase == "carry":  # over the channel's axis, before the near opening
            target, g = near_high, self.squeeze
            if np.linalg.norm(ee - near_high) < 0.01 or self._t > 150:
                self._next("skim")
        if self.phase == "skim":
            target, g = near_low, self.squeeze
            if np.linalg.norm(ee - near_low) < 0.008 or self._t > 60:
                self._next("drag")
        if self.phase == "drag":  # along the axis over the clip: the hanging rope trails into the channel
            target, g = goal_skim, self.squeeze
            if np.linalg.norm(ee - goal_skim) < 0.008 or self._t > 120:
                self._next("lower")
        if self.phase == "lower":
            target, g = goal_low, self.squeeze
            if np.linalg.norm(ee - goal_low) < 0.008 or self._t > 60:
                self._next("release")
        if self.phase == "release":
            target, g = goal_low, 0.0
            if self._t > self.settle_steps:
                self._next("retreat")
        if self.phase == "retreat":
            target, g = np.r_[self._goal, self.carry_height], 0.0
        target = self._wp.toward(
            target, self.holding_speed, self.phase in ("lift", "carry", "skim", "drag", "lower")
        )
        return np.r_[target, self._quat, g].astype(np.float32)
