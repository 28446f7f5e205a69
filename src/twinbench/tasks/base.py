"""What every task over a twin shares: initial states declared as data, the success window, and the
`TwinTask` base class (rules over a built twin; `twinbench.env.TwinEnv` drives it).

A task names the objects it needs by role (`roles`: role -> object name in the twin, overridable), states
where episodes start (planar offsets of each role's object from its rest pose in the twin), and judges
each frame (`frame`), rewards it and exposes the privileged state (object poses, particles, a flat
`environment_state` vector for scripted experts).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinbench.transforms import axis_angle_to_matrix


def offset_pose(rest_pose: np.ndarray, offset) -> np.ndarray:
    """`rest_pose` moved by a planar offset (dx, dy, dtheta): rotated by dtheta about the world z axis
    through the object's origin, then translated by (dx, dy, 0)."""
    dx, dy, dth = (float(v) for v in offset)
    out = np.array(rest_pose, dtype=np.float64)
    out[:3, :3] = axis_angle_to_matrix(np.array([0.0, 0.0, 1.0]), np.array(dth)) @ out[:3, :3]
    out[:3, 3] += (dx, dy, 0.0)
    return out


@dataclass(frozen=True, eq=False)
class InitialStates:
    """Where episodes start: per role, planar offsets (dx, dy, dtheta) from the object's rest pose.

    `grid[role]` is (N, 3), the same N for every role (row i of each is grid state i); `low[role]` and
    `high[role]` bound the uniform sampler used for large runs.
    """

    grid: dict[str, np.ndarray]
    low: dict[str, tuple[float, float, float]]
    high: dict[str, tuple[float, float, float]]

    def __post_init__(self) -> None:
        sizes = {role: np.asarray(g).shape for role, g in self.grid.items()}
        if (
            not sizes
            or len({s[0] for s in sizes.values()}) != 1
            or any(len(s) != 2 or s[1] != 3 for s in sizes.values())
        ):
            raise ValueError(
                f"InitialStates.grid: every role needs an (N, 3) array with the same N, got {sizes}"
            )
        if set(self.low) != set(self.grid) or set(self.high) != set(self.grid):
            raise ValueError("InitialStates: low and high need the same roles as grid")

    def __len__(self) -> int:
        return int(next(iter(self.grid.values())).shape[0])

    @staticmethod
    def product(grids: dict[str, np.ndarray], low: dict, high: dict, fastest: str = "last") -> InitialStates:
        """Every combination of the roles' offsets: with `fastest="last"` the first role varies slowest,
        with `fastest="first"` the first role varies fastest (the reference study's order: state i has
        object offset i % n_object and the collider's offset i // n_object)."""
        if fastest not in ("first", "last"):
            raise ValueError(f"fastest must be 'first' or 'last', got {fastest!r}")
        roles = list(grids)
        order = roles if fastest == "last" else roles[::-1]
        idx = np.stack(np.meshgrid(*[np.arange(len(grids[r])) for r in order], indexing="ij"), -1)
        idx = idx.reshape(-1, len(roles))
        if fastest == "first":
            idx = idx[:, ::-1]
        return InitialStates({r: np.asarray(grids[r])[idx[:, k]] for k, r in enumerate(roles)}, low, high)

    def grid_offsets(self, index: int) -> dict[str, np.ndarray]:
        if not 0 <= index < len(self):
            raise ValueError(f"grid state {index} is outside [0, {len(self)})")
        return {role: np.asarray(g[index], dtype=np.float64) for role, g in self.grid.items()}

    def sample_offsets(self, seed: int) -> dict[str, np.ndarray]:
        """Uniform offsets within [low, high] per role, drawn from `seed` (roles in declaration order)."""
        rng = np.random.default_rng(seed)
        return {
            role: rng.uniform(np.asarray(self.low[role], float), np.asarray(self.high[role], float))
            for role in self.grid
        }


class SuccessWindow:
    """Success when the per-frame condition held in at least `min_hits` of the last `window` frames (the
    reference study's `count >= 30` over its last 100 frames)."""

    def __init__(self, window: int = 100, min_hits: int = 30):
        if window <= 0 or not 1 <= min_hits <= window:
            raise ValueError(f"need window > 0 and 1 <= min_hits <= window, got {window}, {min_hits}")
        self.window, self.min_hits = window, min_hits
        self._hits: list[bool] = []

    def reset(self) -> None:
        self._hits.clear()

    def update(self, hit: bool) -> bool:
        self._hits.append(bool(hit))
        if len(self._hits) > self.window:
            self._hits.pop(0)
        return self.success

    @property
    def success(self) -> bool:
        return sum(self._hits) >= self.min_hits


class TwinTask:
    """Rules over a twin. Subclasses set the class attributes (`name`, the gymnasium `env_id`,
    `description`, ...), implement the methods below and are declared once with
    `twinbench.tasks.register_task(MyTask, make_expert=...)`; the grid size is `len(initial_states)`.

    Lifecycle (driven by TwinEnv): `setup(twin, state)` once after the twin is built (precompute goals,
    check the objects), then per episode `reset(twin, state, offsets)`, and per step `frame(twin,
    state)` -> (hit, metrics), `reward(metrics)`, `privileged(twin, state, metrics)`.
    """

    name: str = ""
    env_id: str = ""  # the gymnasium id, "twinbench/MyTask-v0"
    description: str = ""
    default_roles: dict[str, str] = {}
    environment_state_dim: int = 0
    # A frozen dataclass of the task's settings, with at least `episode_seconds`, `success_window` and
    # `success_min_hits` (TwinEnv routes keyword arguments to it by its fields).
    settings_cls: type

    def __init__(self, roles: dict[str, str] | None = None, **settings):
        self.roles = dict(self.default_roles)
        unknown = sorted(set(roles or {}) - set(self.roles))
        if unknown:
            raise ValueError(f"task {self.name!r}: unknown role(s) {unknown}; roles: {sorted(self.roles)}")
        self.roles.update(roles or {})
        self.settings = self.settings_cls(**settings)

    # --- to implement ---------------------------------------------------------------------------------
    initial_states: InitialStates

    def default_twin(self, preset: str, **cell_settings):
        """The built-in cell of this task as a TwinSpec."""
        raise NotImplementedError

    def controller_overrides(self) -> dict:
        """ControllerConfig fields this task requires of any twin (e.g. the action mode)."""
        return {}

    def setup(self, twin, state) -> None:
        self.check_twin(twin)

    def reset(self, twin, state, offsets: dict[str, np.ndarray]) -> None:
        """Robot at `self.q_start` (set by `setup`), the roles' objects moved by `offsets`."""
        twin.reset(state, self.q_start, self.object_poses(twin, offsets))

    def frame(self, twin, state) -> tuple[bool, dict]:
        raise NotImplementedError

    def reward(self, metrics: dict) -> float:
        return 0.0

    def privileged(self, twin, state, metrics: dict) -> dict:
        """Poses of every role's object (best-fit rigid pose) or collider, keyed by role."""
        return {
            "object_poses": {
                role: (
                    twin.object_pose(state, name)
                    if name in twin.object_names
                    else twin.collider_pose(state, name)
                )
                for role, name in self.roles.items()
            }
        }

    def decorate(self, frames: dict[str, np.ndarray]) -> None:
        """Draw task overlays into the uint8 camera images (in place)."""

    def action_bounds(self, twin) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError

    # --- shared ----------------------------------------------------------------------------------------
    def check_twin(self, twin) -> None:
        present = set(twin.object_names) | set(twin.collider_names)
        missing = {role: name for role, name in self.roles.items() if name not in present}
        if missing:
            raise ValueError(
                f"task {self.name!r} needs object(s) {sorted(missing.values())} "
                f"(roles {sorted(missing)}) but "
                f"twin {twin.spec.name!r} has {twin.object_names}; rename the objects in twin.json or pass "
                f"roles={{ROLE: OBJECT}}"
            )

    def object_poses(self, twin, offsets: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """World poses of the roles' objects (or colliders) for planar `offsets` from their rest poses."""
        return {
            self.roles[role]: offset_pose(self.rest_pose(twin, role), off) for role, off in offsets.items()
        }

    def rest_pose(self, twin, role: str) -> np.ndarray:
        """The rest pose in the twin of the object or collider playing `role`."""
        name = self.roles[role]
        if name in twin.object_names:
            return twin.spec.object(name).rest_pose
        return next(c.pose for c in twin.spec.colliders if c.name == name)

    def start_configuration(self, twin, position, quat) -> np.ndarray:
        """The robot configuration (IK from home) with its end-effector at `position`, `quat` (wxyz); for
        an arm of fewer than 6 joints the turn about the vertical is free (`free_yaw_axis`)."""
        from twinbench.robot.ik import free_yaw_axis, solve_ik
        from twinbench.transforms import pose_matrix

        target = pose_matrix(np.asarray(position, np.float64), np.asarray(quat, np.float64))
        free = free_yaw_axis(twin.robot, quat)
        res = solve_ik(twin.robot, target, twin.robot.home_q, free_axis=free)
        if not res.converged:
            turn = ", any turn about the vertical" if free is not None else ""
            raise ValueError(
                f"{self.name}: the task's start pose (end effector {twin.robot.ee_link!r} at "
                f"{tuple(float(v) for v in position)} m in the robot's base frame, orientation wxyz "
                f"{tuple(float(v) for v in quat)}{turn}) is not reachable by {twin.robot.name} (the closest "
                f"configuration found is {1000 * float(res.pos_err):.1f} mm and "
                f"{np.degrees(float(res.rot_err)):.1f} deg away); the task needs an arm that reaches it")
        return res.q


TOOL_LINK = "tcp"  # the tool point's link in the built-in arms (the gripper's: 15 mm above its fingertips)
DOWN_QUAT = (0.0, 1.0, 0.0, 0.0)  # wxyz: the tool pointing down, its x along world x


def tool_offset(robot) -> np.ndarray:
    """(3,) position of the tool point (link `tcp`) in the end-effector frame: where the end-effector is
    the flange (the reference study's `link_eef`), the tool point 13 cm below it on the built-in gripper;
    zeros where the end-effector is the tool point itself or the robot has no `tcp` link."""
    if TOOL_LINK not in robot.link_names or robot.ee_link == TOOL_LINK:
        return np.zeros(3)
    q = robot.home_q
    return (np.linalg.inv(robot.ee_pose(q)) @ robot.link_pose(q, TOOL_LINK))[:3, 3].copy()


class GraspTask(TwinTask):
    """A task for the gripper arm: absolute `[x, y, z, qw, qx, qy, qz, gripper]` actions of the twin's
    end-effector frame (`RobotSpec.ee_link`: the flange in the reference cells, as in the reference study;
    the tool point `tcp` in the small cells and in twins that name no end-effector). The settings'
    `workspace` box and `start_position` (pointing down, gripper open) are of the tool point: with the
    gripper pointing down, the end-effector's box and start are shifted by the tool offset (`tool_offset`;
    13 cm up for the flange). `info["privileged"]["tool_pose"]` is the tool point's world pose."""

    def controller_overrides(self) -> dict:
        return {"action_mode": "absolute"}

    def _down_shift(self, twin) -> np.ndarray:
        """The end-effector's position minus the tool point's with the tool pointing down."""
        from twinbench.transforms import quat_to_matrix

        return -quat_to_matrix(np.array(DOWN_QUAT)) @ tool_offset(twin.robot)

    def action_bounds(self, twin) -> tuple[np.ndarray, np.ndarray]:
        shift = self._down_shift(twin)
        lo, hi = (np.asarray(b, np.float64) + shift for b in self.settings.workspace)
        return np.array([*lo, -1, -1, -1, -1, 0], np.float32), np.array([*hi, 1, 1, 1, 1, 1], np.float32)

    def setup(self, twin, state) -> None:
        super().setup(twin, state)
        start = np.asarray(self.settings.start_position, np.float64) + self._down_shift(twin)
        q = self.start_configuration(twin, start, DOWN_QUAT)
        self.q_start = twin.robot.set_gripper(q, 0.0)
        self.tool_offset = tool_offset(twin.robot)

    def privileged(self, twin, state, metrics: dict) -> dict:
        out = super().privileged(twin, state, metrics)
        ee = twin.robot.ee_pose(state.robot.q)
        ee[:3, 3] += ee[:3, :3] @ self.tool_offset
        out["tool_pose"] = ee
        return out
