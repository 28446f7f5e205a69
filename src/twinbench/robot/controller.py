"""Controller mimicking the real robot's joint-velocity tracking and gripper force latch (DESIGN §5).

Per env step (30 Hz): target pose from the action -> IK warm-started at the current q -> joint delta
clamped to an L2 norm of `max_joint_delta` -> `v = dq / 0.02 * 0.15` -> `q += v / 30`. The gripper
command (1 = closed) moves at most `gripper_rate` per step and stops closing while BOTH fingers' contact
force magnitudes exceed `grasp_force_threshold` (latched); it releases when the command opens or a force
drops below the threshold. The controller knows nothing about the physics: the caller passes the
fingers' contact forces from the previous frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinbench.robot.ik import IKResult, free_yaw_axis, solve_ik, weighted_error
from twinbench.robot.model import RobotModel
from twinbench.transforms import matrix_to_quat, pose_matrix, rotvec_to_matrix

ACTION_MODES = ("absolute", "relative", "planar")


@dataclass(frozen=True)
class ControllerConfig:
    """Velocity-control mimic parameters (defaults: the reference cell)."""

    action_mode: str = "absolute"  # absolute [x,y,z,qw,qx,qy,qz,g] | relative [dp, rotvec, g] | planar [x,y]
    max_joint_delta: float = 0.10  # rad, L2 norm of the IK joint delta
    velocity_gain: float = 0.15  # v = dq / velocity_dt * velocity_gain
    velocity_dt: float = 0.02  # s
    control_hz: float = 30.0  # q += v / control_hz
    gripper_rate: float = 2.0 / 30.0  # max change of the gripper command per step
    grasp_force_threshold: float = 3e4  # PhysTwin units, per finger
    planar_height: float = 0.02  # m, end-effector z for planar pushing
    planar_quat: tuple[float, float, float, float] = (0.0, 1.0, 0.0, 0.0)  # wxyz, pointing down
    ik_max_iters: int = 60
    ik_restarts: int = 4

    def __post_init__(self) -> None:
        if self.action_mode not in ACTION_MODES:
            raise ValueError(f"action_mode: expected one of {ACTION_MODES}, got {self.action_mode!r}")
        for name in ("max_joint_delta", "velocity_gain", "velocity_dt", "control_hz", "gripper_rate"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name}: must be > 0, got {getattr(self, name)}")
        try:
            quat = np.asarray(self.planar_quat, dtype=np.float64)
        except (TypeError, ValueError):
            quat = np.zeros(0)
        if quat.shape != (4,) or not np.all(np.isfinite(quat)) or not np.linalg.norm(quat) > 1e-6:
            raise ValueError(f"planar_quat: expected a wxyz quaternion (4 finite numbers, not all 0), got "
                             f"{self.planar_quat!r}")

    @property
    def action_dim(self) -> int:
        return {"absolute": 8, "relative": 7, "planar": 2}[self.action_mode]


@dataclass
class ControllerState:
    """What the controller carries from one step to the next."""

    q: np.ndarray  # (n_q,) current configuration (gripper joint included)
    gripper: float  # gripper command in [0, 1] (1 = closed)
    latched: bool = False
    restart_cache: tuple | None = None  # (target, IKResult) of the last target that needed restarts

    def copy(self) -> ControllerState:
        return ControllerState(self.q.copy(), self.gripper, self.latched, self.restart_cache)


@dataclass
class RobotCommand:
    """What the controller asks of the robot for one frame."""

    q: np.ndarray  # (n_q,) joint targets reached at the end of this frame (gripper joint included)
    q_prev: np.ndarray  # (n_q,) configuration at the start of the frame (for substep interpolation)
    joint_velocity: np.ndarray  # (n_arm,) rad/s commanded on the arm joints
    gripper: float  # gripper command in [0, 1] after rate limit and latch (1 = closed)
    gripper_opening: float  # m between the fingers (0 without a gripper)
    latched: bool  # gripper holding: both finger forces above the threshold
    target_pose: np.ndarray  # (4, 4) end-effector target of this frame
    ik_converged: bool


class RobotController:
    """Velocity-control mimic over a RobotModel: `advance(state, action, finger_forces)` -> RobotCommand.

    `reset(q0)` / `step(action, finger_forces)` / `q` / `gripper` / `latched` work on the controller's own
    `state`."""

    def __init__(
        self, model: RobotModel, config: ControllerConfig | None = None, q0: np.ndarray | None = None
    ):
        self.model = model
        self.config = config or ControllerConfig()
        # planar pushing with an arm of fewer than 6 joints: the turn about the vertical is left free
        self.free_axis = (free_yaw_axis(model, self.config.planar_quat)
                          if self.config.action_mode == "planar" else None)
        self.reset(q0)

    def initial_state(self, q0: np.ndarray | None = None) -> ControllerState:
        """A state at q0 (default: the model's home, gripper command as encoded there), unlatched."""
        q = self.model.home_q if q0 is None else self.model.check_q(q0, "q0")
        if q.ndim != 1:
            raise ValueError(f"q0: expected shape ({self.model.n_q},), got {q.shape}")
        q = self.model.clip_q(q.copy())
        return ControllerState(q, float(np.clip(self.model.gripper_closedness(q), 0.0, 1.0)))

    def reset(self, q0: np.ndarray | None = None) -> None:
        """Set the controller's own state to `initial_state(q0)`."""
        self.state = self.initial_state(q0)

    @property
    def q(self) -> np.ndarray:
        return self.state.q

    @property
    def gripper(self) -> float:
        return self.state.gripper

    @property
    def latched(self) -> bool:
        return self.state.latched

    # ----------------------------------------------------------------- observation
    def ee_pose(self, state: ControllerState | None = None) -> np.ndarray:
        return self.model.ee_pose((state or self.state).q)

    def ee_state(self, state: ControllerState | None = None) -> np.ndarray:
        """Policy observation: [x, y, z, qw, qx, qy, qz, gripper] ([x, y] in planar mode)."""
        state = state or self.state
        t = self.model.ee_pose(state.q)
        if self.config.action_mode == "planar":
            return t[:2, 3].copy()
        return np.concatenate([t[:3, 3], matrix_to_quat(t[:3, :3]), [state.gripper]])

    # ----------------------------------------------------------------- action -> target
    def target_from_action(self, action: np.ndarray, state: ControllerState | None = None
                           ) -> tuple[np.ndarray, float]:
        """Validate an action and return (target pose (4, 4), gripper command in [0, 1])."""
        state = state or self.state
        cfg = self.config
        a = np.asarray(action, dtype=np.float64)
        if a.shape != (cfg.action_dim,):
            raise ValueError(
                f"action: expected shape ({cfg.action_dim},) for action_mode {cfg.action_mode!r}, "
                f"got {a.shape}"
            )
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action: contains NaN or inf: {a}")
        if cfg.action_mode == "absolute":
            quat = a[3:7]
            if np.linalg.norm(quat) < 1e-6:
                raise ValueError("action: quaternion a[3:7] (wxyz) has zero norm")
            return pose_matrix(a[:3], quat), float(np.clip(a[7], 0.0, 1.0))
        if cfg.action_mode == "relative":
            # Translation in the world frame; rotation vector in the world frame about the EE origin.
            cur = self.model.ee_pose(state.q)
            t = np.eye(4)
            t[:3, 3] = cur[:3, 3] + a[:3]
            t[:3, :3] = rotvec_to_matrix(a[3:6]) @ cur[:3, :3]
            return t, float(np.clip(a[6], 0.0, 1.0))
        pos = np.array([a[0], a[1], cfg.planar_height])
        return pose_matrix(pos, np.asarray(cfg.planar_quat)), state.gripper

    # ----------------------------------------------------------------- step
    def step(self, action: np.ndarray, finger_forces=None) -> RobotCommand:
        """`advance` the controller's own state."""
        return self.advance(self.state, action, finger_forces)

    def advance(self, state: ControllerState, action: np.ndarray, finger_forces=None) -> RobotCommand:
        """Advance `state` (in place) by one frame. `finger_forces`: (f_left, f_right) contact forces
        (scalars or 3-vectors) of the previous frame."""
        return self.advance_worlds([state], [action], [finger_forces])[0]

    def advance_worlds(
        self, states: list[ControllerState], actions: list, finger_forces: list
    ) -> list[RobotCommand]:
        """`advance` every world's state, with one batched IK solve for all of them (each world's command
        is the one `advance` alone gives)."""
        cfg = self.config
        model = self.model
        goals = [self.target_from_action(a, s) for s, a in zip(states, actions, strict=True)]
        batch = solve_ik(model, np.stack([t for t, _ in goals]), np.stack([s.q for s in states]),
                         max_iters=cfg.ik_max_iters, restarts=0, free_axis=self.free_axis)
        cmds = []
        for i, (state, (target, g_cmd), forces) in enumerate(zip(states, goals, finger_forces, strict=True)):
            warm = IKResult(batch.q[i], bool(batch.converged[i]), batch.pos_err[i], batch.rot_err[i],
                            batch.iterations)
            cmds.append(self._command(state, target, g_cmd, self._solve(state, target, warm), forces))
        return cmds

    def _command(self, state: ControllerState, target: np.ndarray, g_cmd: float, ik: IKResult,
                 finger_forces) -> RobotCommand:
        """Velocity-control mimic toward the IK solution and the gripper latch; updates `state`."""
        cfg = self.config
        model = self.model
        q_prev = state.q.copy()
        arm = model.arm_q_indices
        dq = ik.q[arm] - state.q[arm]
        norm = float(np.linalg.norm(dq))
        if norm > cfg.max_joint_delta:
            dq *= cfg.max_joint_delta / norm
        velocity = dq / cfg.velocity_dt * cfg.velocity_gain
        q = state.q.copy()
        q[arm] = q[arm] + velocity / cfg.control_hz
        q = model.clip_q(q)

        state.latched = self._both_fingers_loaded(finger_forces)
        delta = float(np.clip(g_cmd - state.gripper, -cfg.gripper_rate, cfg.gripper_rate))
        if state.latched and delta > 0:
            delta = 0.0  # holding: stop closing, opening still allowed
        state.gripper = float(np.clip(state.gripper + delta, 0.0, 1.0))
        q = model.set_gripper(q, state.gripper)
        state.q = q
        return RobotCommand(
            q=q.copy(),
            q_prev=q_prev,
            joint_velocity=velocity,
            gripper=state.gripper,
            gripper_opening=float(model.gripper_opening(q)),
            latched=state.latched,
            target_pose=target,
            ik_converged=bool(ik.converged),
        )

    def _solve(self, state: ControllerState, target: np.ndarray, ik: IKResult) -> IKResult:
        """The warm-started IK result `ik` (at the current q), or, for a new target it misses, the random
        restarts' result when better.

        The restart result for the latest such target is cached in the state: a policy holding an
        unreachable (or hard) target does not pay for restarts every frame, and the choice stays
        deterministic.
        """
        cfg = self.config
        if ik.converged or cfg.ik_restarts == 0:
            return ik
        cached = state.restart_cache
        if cached is None or not np.array_equal(cached[0], target):
            cached = (
                target.copy(),
                solve_ik(self.model, target, state.q, max_iters=cfg.ik_max_iters, restarts=cfg.ik_restarts,
                         free_axis=self.free_axis),
            )
            state.restart_cache = cached
        best = cached[1]
        if weighted_error(best.pos_err, best.rot_err) < weighted_error(ik.pos_err, ik.rot_err):
            return best
        return ik

    def _both_fingers_loaded(self, finger_forces) -> bool:
        if finger_forces is None:
            return False
        if len(finger_forces) != 2:
            raise ValueError(f"finger_forces: expected (f_left, f_right), got {len(finger_forces)} entries")
        mags = []
        for name, f in zip(("f_left", "f_right"), finger_forces, strict=True):
            f = np.asarray(f, dtype=np.float64)
            if f.shape not in ((), (3,)):
                raise ValueError(
                    f"finger_forces {name}: expected a scalar or a 3-vector, got shape {f.shape}"
                )
            if not np.all(np.isfinite(f)):
                raise ValueError(f"finger_forces {name}: contains NaN or inf")
            mags.append(float(np.linalg.norm(f)))
        return min(mags) > self.config.grasp_force_threshold
