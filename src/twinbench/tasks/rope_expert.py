"""Scripted rope-routing expert: grasp the marked end, lift, carry it to the channel's axis before the
near opening, drag it along the axis just above the clip (the hanging rope trails into the channel),
lower it beyond the far opening, release, and keep clear. A rope lying beside the channel's axis (its
centroid more than `lay_side` from it) is first lifted high, hanging, carried to the axis `lay_length`
before the near opening with the hand turned so that the rope leaves the fingers backwards along the axis,
and lowered there: the rope touches down behind the hand, and the drag pulls it along the axis into the
channel.

It plans from `obs["environment_state"]` (see tasks.rope_routing): the marked end, a rope point 4 cm from
it (the rope's direction at the end, for the finger orientation), the rope's centroid and the clip pose.
"""

from __future__ import annotations

import numpy as np

from twinbench.tasks.gripper_expert import (
    TCP_ABOVE_TIPS,
    GripperExpert,
    Leg,
    down_quat,
    grasp_quat,
    grasp_yaw,
)


class RopeExpert(GripperExpert):
    """See the module docstring. `channel_length` and `channel_depth` (m) are the clip channel's (the
    twin's `ColliderSpec.channel`, read by `tasks.rope_routing.make_expert`). `squeeze` is the gripper
    command while holding: fingers 6.8 mm apart, pressing into the 8-10 mm rope (closing fully would push
    particles into the finger meshes, where they stay trapped)."""

    def __init__(self, *, channel_length: float, channel_depth: float, grip_inset: float = 0.012,
                 carry_height: float = 0.12, beyond: float = 0.07, close_steps: int = 20,
                 settle_steps: int = 25, holding_speed: float = 0.006, squeeze: float = 0.92,
                 lay_side: float = 0.1, lay_lift: float = 0.24, lay_length: float = 0.12,
                 tool_offset=(0.0, 0.0, 0.0)):
        self.channel_length, self.channel_depth = channel_length, channel_depth
        self.lay_side, self.lay_lift, self.lay_length = lay_side, lay_lift, lay_length
        self.grip_inset, self.carry_height, self.beyond = grip_inset, carry_height, beyond
        self.close_steps, self.settle_steps, self.squeeze = close_steps, settle_steps, squeeze
        super().__init__(holding_speed, tool_offset)

    def plan(self, s: np.ndarray) -> list[Leg]:
        end, along, centroid, clip = s[0:3], s[3:6], s[6:9], s[9:12]
        direction = end[:2] - along[:2]
        direction /= max(np.linalg.norm(direction), 1e-9)
        q = q0 = grasp_quat(direction)
        grip = np.r_[end[:2] - self.grip_inset * direction, TCP_ABOVE_TIPS + 0.002]
        axis = np.array([-np.sin(clip[2]), np.cos(clip[2])])  # the channel: clip frame y in the world
        if axis @ (clip[:2] - centroid[:2]) < 0:
            axis = -axis
        near = clip[:2] - axis * (self.channel_length / 2 + 0.03)  # before the near opening
        goal = clip[:2] + axis * (self.channel_length / 2 + self.beyond)  # beyond the far one
        skim = self.channel_depth + 0.02 + TCP_ABOVE_TIPS  # fingertips 2 cm above the clip's walls
        low = self.channel_depth * 0.5 + TCP_ABOVE_TIPS
        g = self.squeeze
        side = abs(axis[0] * (centroid[1] - clip[1]) - axis[1] * (centroid[0] - clip[0]))
        if side > self.lay_side:  # the rope lies beside the channel's axis: lay it along the axis first
            high = self.carry_height + self.lay_lift  # most of the rope hangs below the hand
            start = near - axis * self.lay_length
            # turned while carrying so that the rope's body (at the grip: -direction) leaves the fingers
            # backwards along the axis: it touches down behind the hand and trails it through the channel
            turn = np.arctan2(direction[0] * axis[1] - direction[1] * axis[0], direction @ axis)
            q = down_quat(grasp_yaw(direction) + turn)
            carry = [
                Leg("lift", np.r_[grip[:2], high], q0, g, tol=0.01, steps=90, slow=True),
                Leg("carry", np.r_[start, high], q, g, tol=0.01, steps=150, slow=True),
                Leg("lay", np.r_[start, skim], q, g, tol=0.008, steps=90, slow=True),
            ]
        else:  # the rope lies along the axis: it trails into the channel behind the hand
            carry = [
                Leg("lift", np.r_[grip[:2], self.carry_height], q, g, tol=0.01, steps=90, slow=True),
                Leg("carry", np.r_[near, self.carry_height], q, g, tol=0.01, steps=150, slow=True),
                Leg("skim", np.r_[near, skim], q, g, tol=0.008, steps=60, slow=True),
            ]
        return [
            Leg("approach", np.r_[grip[:2], 0.08], q0, 0.0, tol=0.01, steps=60),
            Leg("descend", grip, q0, 0.0, tol=0.006, steps=60),
            Leg("close", grip, q0, g, steps=self.close_steps),
            *carry,
            Leg("drag", np.r_[goal, skim], q, g, tol=0.008, steps=120, slow=True),
            Leg("lower", np.r_[goal, low], q, g, tol=0.008, steps=60, slow=True),
            Leg("release", np.r_[goal, low], q, 0.0, steps=self.settle_steps),
            Leg("retreat", np.r_[goal, self.carry_height], q, 0.0),
        ]
