"""Scripted toy-packing expert: grasp the torso between the limbs, lift, carry over the box turning the
toy to the box's orientation, lower it in (the walls fold the soft limbs up), release, keep clear.

It acts from `obs["environment_state"]` (see tasks.toy_packing): the toy's pose (origin at the torso's
bottom centre) and the box's pose.
"""

from __future__ import annotations

import numpy as np

from twinbench.policies.base import PolicyError
from twinbench.tasks.gripper_expert import TCP_ABOVE_TIPS, Waypoint, grasp_quat


class ToyExpert:
    """Phase machine over `environment_state`; see the module docstring."""

    uses_environment_state = True

    def __init__(
        self,
        *,
        grip_height: float = 0.012,
        carry_height: float = 0.12,
        drop_height: float = 0.0,
        close_steps: int = 20,
        settle_steps: int = 20,
        holding_speed: float = 0.006,
        hover_steps: int = 15,
    ):
        self.grip_height, self.carry_height, self.drop_height = grip_height, carry_height, drop_height
        self.close_steps, self.settle_steps, self.holding_speed = close_steps, settle_steps, holding_speed
        self.hover_steps = hover_steps
        self.reset()

    def reset(self) -> None:
        self.phase, self._t, self._grip, self._quat, self._box, self._box_quat = (
            "approach",
            0,
            None,
            None,
            None,
            None,
        )
        self._wp = Waypoint()

    def _next(self, phase: str) -> None:
        self.phase, self._t = phase, 0

    def select_action(self, obs) -> np.ndarray:
        if "environment_state" not in obs:
            raise PolicyError(
                "the toy expert needs obs['environment_state'] (make the env with "
                "environment_state=True, or let the evaluation runner add it)"
            )
        s = np.asarray(obs["environment_state"], dtype=np.float64)
        toy, toy_th, box = s[0:3], s[3], s[4:7]
        ee = np.asarray(obs["agent_pos"], dtype=np.float64)[:3]
        self._t += 1
        if self._grip is None:  # tcp x along the toy's x: the fingers close across the torso, between limbs
            self._grip = np.r_[toy[:2], toy[2] + self.grip_height + TCP_ABOVE_TIPS]
            self._quat = grasp_quat((np.cos(toy_th), np.sin(toy_th)))
            self._box = box.copy()
            self._box_quat = grasp_quat((np.cos(box[2]), np.sin(box[2])))
        above = np.r_[self._grip[:2], 0.10]
        over_box = np.r_[self._box[:2], self.carry_height]
        in_box = np.r_[self._box[:2], self.drop_height + self.grip_height + TCP_ABOVE_TIPS]
        target, quat, g = above, self._quat, 0.0
        if self.phase == "approach" and (np.linalg.norm(ee - above) < 0.01 or self._t > 60):
            self._next("descend")
        if self.phase == "descend":
            target = self._grip
            if np.linalg.norm(ee - self._grip) < 0.006 or self._t > 60:
                self._next("close")
        if self.phase == "close":
            target, g = self._grip, 1.0
            if self._t > self.close_steps:
                self._next("lift")
        if self.phase == "lift":
            target, g = np.r_[self._grip[:2], self.carry_height], 1.0
            if abs(ee[2] - self.carry_height) < 0.01 or self._t > 90:
                self._next("carry")
        if self.phase == "carry":
            target, quat, g = over_box, self._box_quat, 1.0
            if np.linalg.norm(ee - over_box) < 0.01 or self._t > 150:
                self._next("hover")
        if self.phase == "hover":  # let the dangling toy stop swinging before it goes in
            target, quat, g = over_box, self._box_quat, 1.0
            if self._t > self.hover_steps:
                self._next("lower")
        if self.phase == "lower":
            target, quat, g = in_box, self._box_quat, 1.0
            if np.linalg.norm(ee - in_box) < 0.008 or self._t > 90:
                self._next("release")
        if self.phase == "release":
            target, quat, g = in_box, self._box_quat, 0.0
            if self._t > self.settle_steps:
                self._next("retreat")
        if self.phase == "retreat":
            target, quat, g = over_box, self._box_quat, 0.0
        target = self._wp.toward(
            target, self.holding_speed, self.phase in ("lift", "carry", "hover", "lower")
        )
        return np.r_[target, quat, g].astype(np.float32)
