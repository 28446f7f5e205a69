"""`push-t` (`twinbench/PushT-v0`): push a rigid spring-mass T-block onto a goal pose (DESIGN §7).

Rules over a twin with an object in the role `block` (default object name `tblock`) whose footprint is its
`outline` in the twin (`ObjectSpec.outline`, in the block's frame), pushed by a robot whose tool tip has a
`tool_radius` (`RobotSpec.tool_radius`; the scripted expert plans with it): state and action are the
pusher tip's `[x, y]` (absolute target in the robot base frame, planar action mode at the cell's pusher
height).
The goal is the setting `goal_pose` = (x, y, theta) when given, else the block's `goal_pose` in the twin,
else its rest pose. Grid: the reference study's 16 states in its order, state i moving the block from its
rest pose by (x, y) = [(-5, -5), (-5, 5), (5, -5), (5, 5)][i // 4] cm and theta = [45, 135, 225, 315][i % 4]
deg; success is a mean squared particle distance to the goal below 0.002 m^2 in at least 30 of the last 100
frames, after 30 settling frames; the
dense reward is the goal footprint's coverage (the fraction of the outline at the goal that the block's
outline covers). The goal is drawn into the front camera image as a
translucent yellow overlay. The built-in cell is `twinbench.twin.cells.push_t_cell` (presets `reference`
and `fast`: the reference study's layout; `small` and `small-fast`: the earlier scaled-down cell).

`environment_state` (privileged, for scripted experts): [x, y, theta, goal_x, goal_y, goal_theta, msd].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinbench.tasks import register_task
from twinbench.tasks.base import InitialStates, TwinTask
from twinbench.transforms import planar_pose, transform_points

GOAL_RGBA = (1.0, 0.85, 0.1, 0.4)  # translucent yellow goal overlay


@dataclass(frozen=True)
class PushTSettings:
    """Task settings (the twin's are in `twinbench.twin.cells.PushTCell`)."""

    episode_seconds: float = 60.0
    goal_pose: tuple[float, float, float] | None = None  # x, y, theta; None: the twin's (goal or rest pose)
    pusher_start: tuple[float, float] = (0.30, -0.20)  # the reference study's init_eef_xyz
    workspace: tuple[float, float, float, float] = (0.2, 0.8, -0.3, 0.3)  # x_min, x_max, y_min, y_max
    success_msd: float = 0.002  # m^2, mean squared particle distance to the goal
    success_window: int = 100
    success_min_hits: int = 30
    settle_steps: int = 30  # physics frames with the robot held before the first observation
    sample_half_range: float = 0.075  # m, large-scale sampling of x and y (any angle)


STUDY_XY = ((-0.05, -0.05), (-0.05, 0.05), (0.05, -0.05), (0.05, 0.05))  # m, the study's cfg/gs/T.yaml
STUDY_THETA = (45.0, 135.0, 225.0, 315.0)  # deg


def grid_initial_states() -> np.ndarray:
    """The reference study's 16 initial states (dx, dy, dtheta) from the block's rest pose, in its index
    order: state i has xy[i // 4] and theta[i % 4] (its `grid_randomization`, `one_to_one: False`)."""
    return np.array([(x, y, np.deg2rad(th)) for x, y in STUDY_XY for th in STUDY_THETA])


def mean_squared_distance(particles: np.ndarray, goal_particles: np.ndarray) -> float:
    """Mean over particles of the squared distance to the same particle at the goal pose (m^2)."""
    d = np.asarray(particles, dtype=np.float64) - np.asarray(goal_particles, dtype=np.float64)
    return float(np.mean(np.sum(d * d, axis=1)))


def pose_xytheta(pose: np.ndarray) -> np.ndarray:
    """(x, y, theta) of a 4x4 pose (theta: rotation about z of its x axis)."""
    return np.array([pose[0, 3], pose[1, 3], np.arctan2(pose[1, 0], pose[0, 0])])


class PushTTask(TwinTask):
    name = "push-t"
    env_id = "twinbench/PushT-v0"
    description = "push the T-shaped block onto the yellow target"
    default_roles = {"block": "tblock"}
    environment_state_dim = 7
    settings_cls = PushTSettings

    def __init__(self, roles=None, **settings):
        super().__init__(roles, **settings)
        h = self.settings.sample_half_range
        self.initial_states = InitialStates(
            {"block": grid_initial_states()}, {"block": (-h, -h, -np.pi)}, {"block": (h, h, np.pi)}
        )

    def default_twin(self, preset: str, **cell_settings):
        from twinbench.twin.cells import push_t_cell

        return push_t_cell(preset, **cell_settings)

    def controller_overrides(self) -> dict:
        return {"action_mode": "planar"}

    def action_bounds(self, twin):
        x0, x1, y0, y1 = self.settings.workspace
        return np.array([x0, y0], np.float32), np.array([x1, y1], np.float32)

    # ------------------------------------------------------------------ setup
    def setup(self, twin, state) -> None:
        super().setup(twin, state)
        block = self.roles["block"]
        s = self.settings
        spec = twin.spec.object(block)
        if spec.outline is None:
            raise ValueError(
                f"task {self.name!r} needs the outline of object {block!r} (its footprint in its own frame) "
                f"but twin {twin.spec.name!r} has none: give the object an `outline` (polygon and height) in "
                "twin.json, or ObjectSpec(outline=twinbench.twin.shapes.Outline(...))"
            )
        if twin.spec.robot.tool_radius is None:
            raise ValueError(
                f"task {self.name!r} needs the radius of the pusher tip but the robot of twin "
                f"{twin.spec.name!r} has none: set robot.tool_radius (m) in twin.json"
            )
        self.outline, self.tool_radius = spec.outline, twin.spec.robot.tool_radius
        if s.goal_pose is not None:
            self.goal = planar_pose(*s.goal_pose)
        else:
            self.goal = (spec.rest_pose if spec.goal_pose is None else spec.goal_pose).copy()
        self.goal_particles = transform_points(self.goal, twin.rest_particles(block))
        # Coverage: centres of a 2 mm grid of cells over the block's footprint (block frame).
        lo, hi = self.outline.bounds()
        gx, gy = np.meshgrid(np.arange(lo[0] + 0.001, hi[0], 0.002), np.arange(lo[1] + 0.001, hi[1], 0.002))
        cells = np.c_[gx.ravel(), gy.ravel(), np.full(gx.size, 0.5 * self.outline.height)]
        self._cover_local = cells[self.outline.contains(cells)]
        ctrl = twin.controller.config
        self.q_start = self.start_configuration(twin, (*s.pusher_start, ctrl.planar_height), ctrl.planar_quat)
        self.overlay_camera = "front" if "front" in twin.cameras else next(iter(twin.cameras))
        self._overlay = self._overlay_mask(twin.camera(state, self.overlay_camera))
        # the goal's pixels as flat indices of an (H, W, 3) image: gathered 4x faster than by the mask
        self._overlay_flat = (np.flatnonzero(self._overlay)[:, None] * 3 + np.arange(3)).ravel()

    def _overlay_mask(self, cam) -> np.ndarray:
        """Pixels of a camera image covered by the goal footprint (projected onto the table)."""
        from matplotlib.path import Path as PolyPath

        polygon = self.outline.polygon
        outline = transform_points(self.goal, np.c_[polygon, np.zeros(len(polygon))])
        p_cam = outline @ cam.world_to_cam[:3, :3].T + cam.world_to_cam[:3, 3]
        uv = np.c_[cam.fx * p_cam[:, 0] / p_cam[:, 2] + cam.cx, cam.fy * p_cam[:, 1] / p_cam[:, 2] + cam.cy]
        jj, ii = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
        inside = PolyPath(uv).contains_points(np.c_[jj.ravel(), ii.ravel()])
        return inside.reshape(cam.height, cam.width)

    # ------------------------------------------------------------------ episode
    def goal_msd(self, twin, state) -> float:
        """Mean squared distance (m^2) of the block's particles to their goal positions."""
        return mean_squared_distance(twin.particles(state, self.roles["block"]), self.goal_particles)

    def coverage(self, twin, state) -> float:
        """Fraction of the goal footprint covered by the block (the dense reward)."""
        pose = twin.object_pose(state, self.roles["block"])
        world = transform_points(self.goal, self._cover_local)
        local = (world - pose[:3, 3]) @ pose[:3, :3]
        local[:, 2] = 0.5 * self.outline.height
        return float(np.mean(self.outline.contains(local, tol=1e-6)))

    def frame(self, twin, state) -> tuple[bool, dict]:
        msd = self.goal_msd(twin, state)
        return msd < self.settings.success_msd, {"msd": msd, "coverage": self.coverage(twin, state)}

    def reward(self, metrics: dict) -> float:
        return metrics["coverage"]

    def privileged(self, twin, state, metrics: dict) -> dict:
        out = super().privileged(twin, state, metrics)
        block = pose_xytheta(out["object_poses"]["block"])
        out["environment_state"] = np.concatenate([block, pose_xytheta(self.goal), [metrics["msd"]]]).astype(
            np.float32
        )
        return out

    def decorate(self, frames: dict[str, np.ndarray]) -> None:
        img = frames.get(self.overlay_camera)
        if img is None:  # that camera is not observed (TwinEnv's `cameras`)
            return
        r, g, b, alpha = GOAL_RGBA
        goal = np.take(img, self._overlay_flat).reshape(-1, 3)  # blend only the goal's pixels
        blended = (1 - alpha) * goal + alpha * 255.0 * np.array([r, g, b], np.float32)
        np.put(img, self._overlay_flat, np.clip(blended + 0.5, 0, 255).astype(np.uint8))


def make_expert(env):
    """The scripted expert, for the twin's block outline and pusher radius; it acts from
    `environment_state` (never the env's internals)."""
    from twinbench.tasks.push_t_expert import PushTExpert

    rules = env.unwrapped.rules
    return PushTExpert(rules.outline, pusher_radius=rules.tool_radius)


register_task(PushTTask, make_expert=make_expert)
