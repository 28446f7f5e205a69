"""Scripted toy-packing expert: grasp the torso between the limbs, lift, carry over the box turning the
toy to the box's orientation, hover until it stops swinging, lower it in (the walls fold the soft limbs
up), release, keep clear.

It plans from `obs["environment_state"]` (see tasks.toy_packing): the toy's pose (origin at the torso's
bottom centre) and the box's pose.
"""

from __future__ import annotations

import numpy as np

from twinbench.tasks.gripper_expert import TCP_ABOVE_TIPS, GripperExpert, Leg, grasp_quat


class ToyExpert(GripperExpert):
    """See the module docstring."""

    def __init__(self, *, grip_height: float = 0.012, carry_height: float = 0.12, drop_height: float = 0.0,
                 close_steps: int = 20, settle_steps: int = 20, holding_speed: float = 0.006,
                 hover_steps: int = 15, tool_offset=(0.0, 0.0, 0.0)):
        self.grip_height, self.carry_height, self.drop_height = grip_height, carry_height, drop_height
        self.close_steps, self.settle_steps, self.hover_steps = close_steps, settle_steps, hover_steps
        super().__init__(holding_speed, tool_offset)

    def plan(self, s: np.ndarray) -> list[Leg]:
        toy, toy_th, box = s[0:3], s[3], s[4:7]
        # tcp x along the toy's x: the fingers close across the torso, between the limbs
        q = grasp_quat((np.cos(toy_th), np.sin(toy_th)))
        q_box = grasp_quat((np.cos(box[2]), np.sin(box[2])))
        grip = np.r_[toy[:2], toy[2] + self.grip_height + TCP_ABOVE_TIPS]
        over_box = np.r_[box[:2], self.carry_height]
        in_box = np.r_[box[:2], self.drop_height + self.grip_height + TCP_ABOVE_TIPS]
        return [
            Leg("approach", np.r_[grip[:2], 0.10], q, 0.0, tol=0.01, steps=60),
            Leg("descend", grip, q, 0.0, tol=0.006, steps=60),
            Leg("close", grip, q, 1.0, steps=self.close_steps),
            Leg("lift", np.r_[grip[:2], self.carry_height], q, 1.0, tol=0.01, steps=90, slow=True),
            Leg("carry", over_box, q_box, 1.0, tol=0.01, steps=150, slow=True),
            Leg("hover", over_box, q_box, 1.0, steps=self.hover_steps, slow=True),
            Leg("lower", in_box, q_box, 1.0, tol=0.008, steps=90, slow=True),
            Leg("release", in_box, q_box, 0.0, steps=self.settle_steps),
            Leg("retreat", over_box, q_box, 0.0),
        ]
