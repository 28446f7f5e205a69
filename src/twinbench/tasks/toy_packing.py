"""`toy-packing` (`twinbench/ToyPacking-v0`): put a plush toy into an open-top box (DESIGN §7).

Rules over a twin with a deformable object in the role `toy` (default `toy`) and a collider in the role
`box` (default `box`). State and action are `[x, y, z, qw, qx, qy, qz, gripper]` (absolute end-effector
pose in the robot base frame, gripper 1 = closed). Grid: the reference study's 20 states in its order,
state i pairing toy offset i % 5 with box offset i // 5 (the toy varies fastest): toy (x, y cm; theta deg)
(0, 0; 0), (-5, 0; -5), (5, 0; 5), (0, -5; -5), (0, 3; 5); box (0, 0; 0), (-5, 0; -5), (5, 0; 5), (0, 5; 5);
the sampler draws uniformly in the study's ranges (toy x in [-5, 5] cm, y in [-5, 3] cm, theta in [-5, 5]
deg; box x in [-5, 5] cm, y in [0, 5] cm, theta in [-5, 5] deg). Episodes last 15 s after 30 settling
frames. Success: at least `inside_fraction` of the toy's particles (98.5 %, the reference's 3050 of 3095)
inside the box's oriented bounding box scaled by 1.05, in at least 30 of the last 100 frames.

`environment_state` (privileged, for the scripted expert): [toy origin x, y, z, toy theta, box x, y,
theta, fraction of particles inside].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinbench.tasks import register_task
from twinbench.tasks.base import GraspTask, InitialStates
from twinbench.tasks.push_t import pose_xytheta
from twinbench.transforms import invert_pose, transform_points

_D5 = float(np.deg2rad(5.0))
# The reference study's cfg/gs/sloth.yaml grids (one_to_one): (dx, dy, dtheta) of the toy and of the box.
STUDY_TOY_GRID = ((0.0, 0.0, 0.0), (-0.05, 0.0, -_D5), (0.05, 0.0, _D5), (0.0, -0.05, -_D5), (0.0, 0.03, _D5))
STUDY_BOX_GRID = ((0.0, 0.0, 0.0), (-0.05, 0.0, -_D5), (0.05, 0.0, _D5), (0.0, 0.05, _D5))


@dataclass(frozen=True)
class ToyPackingSettings:
    """Task settings (the built-in twin's are `twinbench.twin.cells.ToyCell`)."""

    episode_seconds: float = 15.0
    inside_fraction: float = 3050 / 3095
    box_scale: float = 1.05
    success_window: int = 100
    success_min_hits: int = 30
    settle_steps: int = 30
    workspace: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.2, -0.4, 0.0),
        (0.8, 0.4, 0.5),
    )
    start_position: tuple[float, float, float] = (0.35, 0.0, 0.25)


class ToyPackingTask(GraspTask):
    name = "toy-packing"
    env_id = "twinbench/ToyPacking-v0"
    description = "pick up the plush toy and pack it into the box"
    default_roles = {"toy": "toy", "box": "box"}
    environment_state_dim = 8
    settings_cls = ToyPackingSettings

    def __init__(self, roles=None, **settings):
        super().__init__(roles, **settings)
        d = np.deg2rad(5.0)
        self.initial_states = InitialStates.product(
            {"toy": np.array(STUDY_TOY_GRID), "box": np.array(STUDY_BOX_GRID)},
            {"toy": (-0.05, -0.05, -d), "box": (-0.05, 0.0, -d)},
            {"toy": (0.05, 0.03, d), "box": (0.05, 0.05, d)},
            fastest="first",
        )

    def default_twin(self, preset: str, **cell_settings):
        from twinbench.twin.cells import toy_packing_cell

        return toy_packing_cell(preset, **cell_settings)

    def setup(self, twin, state) -> None:
        super().setup(twin, state)
        box = next(c for c in twin.spec.colliders if c.name == self.roles["box"])
        lo, hi = box.vertices.min(0), box.vertices.max(0)
        self.box_center = (lo + hi) / 2  # the box's bounding box in its own frame
        self.box_half = (hi - lo) / 2 * self.settings.box_scale
        self.box_height = float(hi[2])  # the walls' top above the table (the expert carries above it)

    def inside(self, twin, state) -> float:
        """Fraction of the toy's particles inside the box's scaled oriented bounding box."""
        box = twin.collider_pose(state, self.roles["box"])
        local = transform_points(invert_pose(box), twin.particles(state, self.roles["toy"])) - self.box_center
        return float(np.mean(np.all(np.abs(local) <= self.box_half, axis=1)))

    def frame(self, twin, state) -> tuple[bool, dict]:
        frac = self.inside(twin, state)
        return frac >= self.settings.inside_fraction, {"inside_fraction": frac}

    def reward(self, metrics: dict) -> float:
        return metrics["inside_fraction"]

    def privileged(self, twin, state, metrics: dict) -> dict:
        out = super().privileged(twin, state, metrics)
        toy, box = out["object_poses"]["toy"], out["object_poses"]["box"]
        out["environment_state"] = np.concatenate(
            [toy[:3, 3], [pose_xytheta(toy)[2]], pose_xytheta(box), [metrics["inside_fraction"]]]
        ).astype(np.float32)
        return out


def make_expert(env):
    """The scripted expert; it acts from `environment_state` (never the env's internals)."""
    from twinbench.tasks.toy_expert import ToyExpert

    rules = env.unwrapped.rules
    # the tool point 7 cm above the walls: the held toy's bottom clears them by 2-3 cm
    return ToyExpert(carry_height=max(0.12, rules.box_height + 0.07), tool_offset=rules.tool_offset)


register_task(ToyPackingTask, make_expert=make_expert)
