"""`rope-routing` (`twinbench/RopeRouting-v0`): route a deformable rope into a clip's channel (DESIGN §7).

Rules over a twin with a spring-mass object in the role `rope` (default object `rope`, its marked end at
the +x end of its own frame) and a collider in the role `clip` (default `clip`) with a `channel` in the
twin (`ColliderSpec.channel`): a channel along the clip frame's y axis, centred on its origin, floor at
z = 0, open at both ends, of the twin's width, depth and length (the settings `channel_width`,
`channel_depth`, `channel_length` override them). State and action are the end-effector pose and gripper,
`[x, y, z, qw, qx, qy, qz, gripper]` (absolute, robot base frame, gripper 1 = closed).

Grid: the reference study's 27 states in its order, state i moving the rope from its rest pose by (x, y) =
[(-5, -5), (-5, 0), (-5, 5), (0, -5), ..., (5, 5)][i // 3] cm and theta = [-10, 0, 10][i % 3] deg; the
sampler draws +-7.5 cm and +-15 deg. Episodes last 30 s after 30 settling frames.
Success: at both openings (the channel's end planes, within the channel's cross-section) at least
`crossing_threshold` rope springs cross, in at least 30 of the last 100 frames.

The threshold: the reference study's `crossing_threshold` = 100 springs per opening (its
calculate_success_rope.py: every spring of the rope, the planes y = y_min and y = y_max of its 3.5 x 3.5 x
3 cm box, within the box's x-z rectangle), capped at a fraction (`crossing_fraction`, default 0.5) of the
springs that cross one cross-section of this twin's straight rope at rest (computed at setup): a rope's
spring count across a section grows with its particle density, and a coarse rope could never reach 100.
The `reference` rope is dense enough (204 springs cross a section: threshold 100); the `fast` rope (180)
gets 90, the small cells' ropes (49 and 13) 25 and 7 ("about half of the rope's section lies inside each
opening").

`environment_state` (privileged, for the scripted expert): [marked end (3), the rope point 4 cm from it
(3), the rope's centroid (3), clip x, y, theta (3), crossings at the two openings (2)].
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinbench.tasks import register_task
from twinbench.tasks.base import GraspTask, InitialStates
from twinbench.transforms import invert_pose, transform_points


@dataclass(frozen=True)
class RopeRoutingSettings:
    """Task settings (the built-in twin's are `twinbench.twin.cells.RopeCell`)."""

    episode_seconds: float = 30.0
    channel_width: float | None = None  # m; None: the clip's channel in the twin
    channel_depth: float | None = None
    channel_length: float | None = None
    crossing_threshold: int = 100
    crossing_fraction: float = 0.5
    success_window: int = 100
    success_min_hits: int = 30
    settle_steps: int = 30
    workspace: tuple[tuple[float, float, float], tuple[float, float, float]] = (
        (0.2, -0.4, 0.0),
        (0.8, 0.4, 0.5),
    )
    start_position: tuple[float, float, float] = (0.35, 0.0, 0.25)  # gripper start, pointing down, open


def count_crossings(
    points: np.ndarray, springs: np.ndarray, plane_y: float, half_width: float, depth: float
) -> int:
    """Springs (M, 2) between `points` (clip frame) that cross the plane y = plane_y within
    |x| <= half_width and 0 <= z <= depth."""
    a, b = points[springs[:, 0]], points[springs[:, 1]]
    da, db = a[:, 1] - plane_y, b[:, 1] - plane_y
    cross = da * db < 0
    t = da[cross] / (da[cross] - db[cross])
    hit = a[cross] + t[:, None] * (b[cross] - a[cross])
    inside = (np.abs(hit[:, 0]) <= half_width) & (hit[:, 2] >= 0.0) & (hit[:, 2] <= depth)
    return int(np.sum(inside))


class RopeRoutingTask(GraspTask):
    name = "rope-routing"
    env_id = "twinbench/RopeRouting-v0"
    description = "pick up the rope by its red end and route it into the green clip"
    default_roles = {"rope": "rope", "clip": "clip"}
    environment_state_dim = 14
    settings_cls = RopeRoutingSettings

    def __init__(self, roles=None, **settings):
        super().__init__(roles, **settings)
        grid = np.array(
            [
                (dx, dy, np.deg2rad(th))
                for dx in (-0.05, 0.0, 0.05)
                for dy in (-0.05, 0.0, 0.05)
                for th in (-10.0, 0.0, 10.0)
            ]
        )
        h, a = 0.075, np.deg2rad(15.0)
        self.initial_states = InitialStates({"rope": grid}, {"rope": (-h, -h, -a)}, {"rope": (h, h, a)})

    def default_twin(self, preset: str, **cell_settings):
        from twinbench.twin.cells import rope_routing_cell

        return rope_routing_cell(preset, **cell_settings)

    def setup(self, twin, state) -> None:
        super().setup(twin, state)
        self.channel = self.clip_channel(twin)
        rope = self.roles["rope"]
        self.springs = twin.object_springs(rope)
        rest = twin.rest_particles(rope)
        xs = np.unique(np.round(rest[:, 0], 9))
        k = len(xs) // 2
        mid = 0.5 * (xs[k - 1] + xs[k])  # between two rings near the middle
        per_section = count_crossings(rest[:, [1, 0, 2]] - [0, mid, 0], self.springs, 0.0, np.inf, np.inf)
        cap = max(1, int(np.ceil(self.settings.crossing_fraction * per_section)))
        self.crossing_threshold = min(self.settings.crossing_threshold, cap)
        self.marked = int(
            np.argmax(rest[:, 0] - 1e-3 * np.abs(rest[:, 1]) - 1e-3 * np.abs(rest[:, 2] - rest[:, 2].mean()))
        )
        near = rest[:, 0] < rest[self.marked, 0] - 0.04
        self.along = int(np.flatnonzero(near)[np.argmax(rest[near, 0] - 1e-3 * np.abs(rest[near, 1]))])

    def clip_channel(self, twin) -> tuple[float, float, float]:
        """(width, depth, length) of the clip's channel: the settings' values, else the twin's."""
        s = self.settings
        given = (s.channel_width, s.channel_depth, s.channel_length)
        if None not in given:
            return given
        clip = self.roles["clip"]
        spec = next((c for c in twin.spec.colliders if c.name == clip), None)
        if spec is None or spec.channel is None:
            raise ValueError(
                f"task {self.name!r} needs the channel of collider {clip!r} but twin {twin.spec.name!r} has "
                "none: give the collider a `channel` [width, depth, length] in twin.json, or pass "
                "channel_width, channel_depth and channel_length"
            )
        return tuple(spec.channel[k] if v is None else v for k, v in enumerate(given))

    def crossings(self, twin, state) -> tuple[int, int]:
        width, depth, length = self.channel
        clip = twin.collider_pose(state, self.roles["clip"])
        local = transform_points(invert_pose(clip), twin.particles(state, self.roles["rope"]))
        half = length / 2
        return tuple(count_crossings(local, self.springs, y, width / 2, depth) for y in (-half, half))

    def frame(self, twin, state) -> tuple[bool, dict]:
        a, b = self.crossings(twin, state)
        hit = min(a, b) >= self.crossing_threshold
        return hit, {"crossings": [a, b], "crossing_threshold": self.crossing_threshold}

    def reward(self, metrics: dict) -> float:
        return float(min(1.0, min(metrics["crossings"]) / metrics["crossing_threshold"]))

    def privileged(self, twin, state, metrics: dict) -> dict:
        out = super().privileged(twin, state, metrics)
        p = twin.particles(state, self.roles["rope"])
        clip = out["object_poses"]["clip"]
        clip_xyt = [clip[0, 3], clip[1, 3], np.arctan2(clip[1, 0], clip[0, 0])]
        out["environment_state"] = np.concatenate(
            [p[self.marked], p[self.along], p.mean(0), clip_xyt, metrics["crossings"]]
        ).astype(np.float32)
        return out


def make_expert(env):
    """The scripted expert; it acts from `environment_state` (never the env's internals)."""
    from twinbench.tasks.rope_expert import RopeExpert

    _, depth, length = env.unwrapped.rules.channel
    return RopeExpert(channel_length=length, channel_depth=depth, tool_offset=env.unwrapped.rules.tool_offset)


register_task(RopeRoutingTask, make_expert=make_expert)
