"""TwinEnv: one gymnasium env for every task over a twin (a built-in cell or a twin directory).

    env = gymnasium.make("twinbench/PushT-v0", preset="fast")               # the task's built-in cell
    env = gymnasium.make("twinbench/PushT-v0", twin="path/to/twin_dir")     # your twin, same rules
    obs, info = env.reset(seed=0, options={"init_state": 3})

Observation: `{"pixels": {camera: HxWx3 uint8}, "agent_pos": float32, "joint_position": float32}` (+
`"gripper_position"` for a robot with a gripper, + `"depth": {camera: HxW float32}` for cameras with depth,
+ `"environment_state"` when made with `environment_state=True`). `joint_position`: the arm's joint angles
(rad, the URDF's arm joints from base to end effector, e.g. 7 for the built-in xArm-7-like arm);
`gripper_position`: (1,) how closed the fingers are, 0 = open, 1 = closed (DROID's convention). `info` holds
`is_success`, `status` ("ok" | "sim_error"), the task's metrics, `grasp` for a gripper ("holding",
"closed_on_air", "closing", "open") and `privileged` (object poses and the task's `environment_state`
vector, for scripted experts and offline rescoring).

Episodes: `reset` places the robot at the task's start configuration and the objects at the grid state,
then steps the physics `settle_steps` frames (a task setting, 30 for the built-in tasks as in the reference
study) with the robot held still before the first observation; the episode's steps count from there. In a
many-world twin (TwinVectorEnv) the worlds reset together settle together; a world reset alone (autoreset,
`reset_mask`, `envs.envs[i].reset()`) settles alone: the frames step every world and the others' particles
are put back, so each world's episode stays the one a TwinEnv runs.

Success rules (`success_rule`, recorded in `info["success_rule"]` and by the evaluation store):
- "final" (default, the reference study's rule): every episode runs its full length; the outcome is the
  task's window criterion (e.g. >= 30 hits in the last 100 frames) at the final frame. `info["is_success"]`
  on each step tells whether the criterion holds over the frames so far.
- "early": the episode terminates as soon as the window criterion holds (a speed option).

Keyword arguments: `task` (registered name or a TwinTask), `twin` (directory or TwinSpec; default: the
task's built-in cell at `preset`), `device`, `success_rule`, `render_views` ("front", "front+wrist", ...:
the cameras `render()` puts side by side; default the first camera), `cameras` (the cameras rendered into
observations, e.g. "front"; default every camera: a policy that sees one camera need not pay for the others),
`environment_state`, `roles`
({role: object}), then the task's settings (e.g. `episode_seconds`) and, for built-in cells only, the
cell's settings (e.g. `pusher_friction`).
"""

from __future__ import annotations

import dataclasses
from dataclasses import replace
from pathlib import Path

import gymnasium
import numpy as np
from gymnasium import spaces

from twinbench._runtime import quiet_warp
from twinbench.physics import SimulationDiverged
from twinbench.tasks.base import SuccessWindow

RESET_OPTIONS = ("init_state", "sampled", "object_poses")
SUCCESS_RULES = ("final", "early")
# (type, lowest, highest) of the keyword arguments a built-in cell turns into its physics step, and of the
# settings every task has; substeps has the range of a twin directory's `sim.substeps`
# (twin.files.FIELD_RANGES, read when checking)
SETTING_RANGES = {"fps": (float, 1.0, 1000.0), "episode_seconds": (float, 1e-3, 86_400.0),
                  "success_window": (int, 1, 10**6), "success_min_hits": (int, 1, 10**6),
                  "settle_steps": (int, 0, 100_000)}


def _numbers(value):
    if isinstance(value, list | tuple | np.ndarray):
        for v in value:
            yield from _numbers(v)
    elif isinstance(value, float | np.floating):
        yield value


def check_settings(settings: dict) -> None:
    """ValueError naming the keyword argument for a setting out of its range (`SETTING_RANGES`, and
    `substeps` as in twin.json), or holding a NaN or infinite number."""
    from twinbench.twin.files import FIELD_RANGES

    ranges = {"substeps": (int, *FIELD_RANGES["sim"]["substeps"][:2]), **SETTING_RANGES}
    for name, (kind, lo, hi) in ranges.items():
        if name not in settings:
            continue
        value = settings[name]
        types = (int, np.integer) if kind is int else (int, float, np.integer, np.floating)
        ok = not isinstance(value, bool) and isinstance(value, types)
        if not ok or not lo <= value <= hi:  # NaN fails too
            raise ValueError(f"{name}={value!r}: expected {'an integer' if kind is int else 'a number'} in "
                             f"[{lo}, {hi}]")
    for name, value in settings.items():
        if not all(np.isfinite(v) for v in _numbers(value)):
            raise ValueError(f"{name}={value!r}: numbers must be finite")


def check_reset_options(options) -> dict:
    """reset(options=...) as a dict; ValueError naming the argument otherwise."""
    if options is None:
        return {}
    if not isinstance(options, dict):
        raise ValueError(f"reset(options=...): expected a dict such as {{'init_state': 3}} or None, got "
                         f"{type(options).__name__}")
    return dict(options)


def _split_settings(task_cls, settings: dict) -> tuple[dict, dict]:
    names = {f.name for f in dataclasses.fields(task_cls.settings_cls)}
    return {k: v for k, v in settings.items() if k in names}, {
        k: v for k, v in settings.items() if k not in names
    }


def resolve_task_twin(task, twin, preset: str, roles: dict | None, settings: dict):
    """(rules, TwinSpec) of an env's arguments: the task's rules with its settings, and the twin (the
    task's built-in cell at `preset` with the cell's settings, a twin directory or a TwinSpec) with the
    controller fields the task requires."""
    from twinbench.tasks import get_task
    from twinbench.twin import TwinSpec, load_twin

    if isinstance(task, str):
        spec = get_task(task)
        if spec.task_cls is None:
            raise ValueError(f"task {task!r} has its own env ({spec.env_id}), not a TwinEnv")
        task_cls = spec.task_cls
    else:
        task_cls = type(task)
    check_settings(settings)
    task_settings, cell_settings = _split_settings(task_cls, settings)
    rules = task if not isinstance(task, str) else task_cls(roles, **task_settings)
    if twin is None:
        twin_spec = rules.default_twin(preset, **cell_settings)
    else:
        if cell_settings:
            raise ValueError(
                f"unknown setting(s) {sorted(cell_settings)} for task {rules.name!r} "
                f"with a twin from disk; task settings: "
                f"{sorted(f.name for f in dataclasses.fields(task_cls.settings_cls))}"
            )
        twin_spec = twin if isinstance(twin, TwinSpec) else load_twin(Path(twin))
    overrides = rules.controller_overrides()
    if overrides:
        twin_spec = replace(twin_spec, controller=replace(twin_spec.controller, **overrides))
    return rules, twin_spec


class TwinEnv(gymnasium.Env):
    """Gymnasium env = a built twin (`twin`, `state`) + a task's rules (`rules`, a TwinTask); see the
    module docstring. `task` / `task_description` hold the task's text."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 30}

    def __init__(
        self,
        task="push-t",
        *,
        twin=None,
        preset: str = "reference",
        device: str = "cpu",
        render_mode: str | None = "rgb_array",
        render_views: str | None = None,
        environment_state: bool = False,
        success_rule: str = "final",
        roles: dict | None = None,
        cameras: str | None = None,
        **settings,
    ):
        from twinbench.twin import build_twin

        quiet_warp()  # library use (gymnasium.make) prints no Warp banner; TWINBENCH_WARP_VERBOSE=1 shows it
        rules, twin_spec = resolve_task_twin(task, twin, preset, roles, settings)
        built, state = build_twin(twin_spec, device)
        self._attach(rules, built, state, render_mode, render_views, environment_state, success_rule, cameras)

    @classmethod
    def _world(cls, rules, twin, state, *args) -> TwinEnv:
        """The env of one world of a many-world twin (see TwinVectorEnv)."""
        env = cls.__new__(cls)
        env._attach(rules, twin, state, *args)
        return env

    def _attach(self, rules, twin, state, render_mode, render_views, environment_state, success_rule,
                cameras=None) -> None:
        if success_rule not in SUCCESS_RULES:
            raise ValueError(f"success_rule must be one of {SUCCESS_RULES}, got {success_rule!r}")
        self.success_rule = success_rule
        self.rules, self.twin, self.state = rules, twin, state
        self._worlds = [state]  # every world state of the twin (TwinVectorEnv sets its list)
        # cameras with a response (a real camera's colour, noise, blur) applied after rendering; noise seeded
        # by reset(seed)
        self.cameras = _camera_list(cameras, twin)  # the cameras rendered into observations
        self._responses = {n: twin.cameras[n].response for n in self.cameras
                           if twin.cameras[n].response is not None}
        self._seed_responses(0)
        self.rules.setup(self.twin, self.state)

        self.render_mode = render_mode
        views = render_views or (self.cameras[0] if self.cameras else "")
        self.render_views = views.split("+") if views else []
        unknown = [v for v in self.render_views if v not in self.cameras]
        if unknown:
            raise ValueError(f"render_views: unknown or unobserved camera(s) {unknown}; observed cameras: "
                             f"{self.cameras}")
        fps = int(round(self.twin.controller.config.control_hz))
        self.metadata = {**self.metadata, "render_fps": fps}
        self._max_episode_steps = int(round(self.rules.settings.episode_seconds * fps))
        self.task_description = self.task = self.rules.description  # `task`: the name LeRobot's loop reads
        self.environment_state = bool(environment_state)

        low, high = self.rules.action_bounds(self.twin)
        self.action_space = spaces.Box(low, high, dtype=np.float32)
        pixels, depth = {}, {}
        for name in self.cameras:
            cam = self.twin.cameras[name]
            h, w = cam.output_hw
            pixels[name] = spaces.Box(0, 255, (h, w, 3), np.uint8)
            if cam.depth:
                depth[name] = spaces.Box(0.0, np.inf, (h, w), np.float32)
        obs_space = {"pixels": spaces.Dict(pixels), "agent_pos": spaces.Box(low, high, dtype=np.float32)}
        robot = self.twin.robot
        arm = robot.arm_q_indices
        obs_space["joint_position"] = spaces.Box(robot.lower[arm].astype(np.float32),
                                                 robot.upper[arm].astype(np.float32), dtype=np.float32)
        if robot.gripper_joint is not None:
            obs_space["gripper_position"] = spaces.Box(0.0, 1.0, (1,), np.float32)
        if depth:
            obs_space["depth"] = spaces.Dict(depth)
        if self.environment_state:
            d = self.rules.environment_state_dim
            obs_space["environment_state"] = spaces.Box(-np.inf, np.inf, (d,), np.float32)
        self.observation_space = spaces.Dict(obs_space)
        rules = self.rules.settings
        self._success = SuccessWindow(rules.success_window, rules.success_min_hits)
        self._steps = 0
        self._status = "ok"
        self._done = False
        self._frames: dict[str, np.ndarray] = {}

    # ------------------------------------------------------------------ gymnasium API
    def reset(self, *, seed=None, options=None):
        self._place(seed, options)
        settle_worlds(self.twin, self._worlds, self.settle_steps, [self.state.world])
        return self._first_observation()

    @property
    def settle_steps(self) -> int:
        """Frames the physics runs with the robot held before an episode's first observation."""
        return int(getattr(self.rules.settings, "settle_steps", 0))

    def _place(self, seed, options) -> None:
        """Robot at its start configuration, the objects at the grid state (or a sampled one)."""
        super().reset(seed=seed)
        if seed is not None:
            self._seed_responses(int(seed))
        options = check_reset_options(options)
        unknown = sorted(set(options) - set(RESET_OPTIONS))
        if unknown:
            raise ValueError(f"reset options: unknown key(s) {unknown}; known: {list(RESET_OPTIONS)}")
        n_grid = len(self.rules.initial_states)
        index = options.get("init_state", 0 if seed is None else int(seed) % n_grid)
        if isinstance(index, bool) or not isinstance(index, int | np.integer):
            raise ValueError(f"options['init_state'] must be an integer grid index, got {index!r}")
        index = int(index)
        if index < 0:
            raise ValueError(f"options['init_state'] must be >= 0, got {index}")
        sampled = bool(options.get("sampled", False)) or index >= n_grid
        states = self.rules.initial_states
        offsets = (
            states.sample_offsets(0 if seed is None else int(seed)) if sampled else states.grid_offsets(index)
        )
        if options.get("object_poses") is not None:
            offsets = {**offsets, **self._measured_offsets(options["object_poses"])}
        self.rules.reset(self.twin, self.state, offsets)

    def _measured_offsets(self, poses) -> dict[str, np.ndarray]:
        """`options["object_poses"]` = {role or object name: (x, y, theta)}, measured planar poses of the
        objects' frames (world, m and rad) -> the offsets from their rest poses that put them there."""
        if not isinstance(poses, dict):
            raise ValueError("options['object_poses'] must be a dict {role or object name: (x, y, theta)}")
        role_of = {obj: role for role, obj in self.rules.roles.items()}
        out = {}
        for key, pose in poses.items():
            role = key if key in self.rules.roles else role_of.get(key)
            try:
                values = np.asarray(pose, dtype=np.float64).ravel()
            except (TypeError, ValueError):
                values = np.zeros(0)
            if role is None or values.shape != (3,) or not np.all(np.isfinite(values)):
                raise ValueError(f"options['object_poses'][{key!r}]: give a role {sorted(self.rules.roles)} "
                                 f"or object {sorted(role_of)} with a finite (x, y, theta), got {pose!r}")
            rest = self.rules.rest_pose(self.twin, role)
            yaw = np.arctan2(rest[1, 0], rest[0, 0])
            out[role] = values - np.array([rest[0, 3], rest[1, 3], yaw])
        return out

    def _seed_responses(self, seed: int) -> None:
        """A noise stream per camera (seed, the camera's index in the twin): a camera's images do not depend
        on which other cameras are observed."""
        index = {name: i for i, name in enumerate(self.twin.cameras)}
        self._response_rngs = {n: np.random.default_rng([seed, index[n]]) for n in self._responses}

    def _first_observation(self):
        self._success.reset()
        self._steps, self._status, self._done = 0, "ok", False
        hit, metrics = self.rules.frame(self.twin, self.state)
        obs = self._observe(metrics)
        info = {
            "is_success": False,
            "status": "ok",
            "success_rule": self.success_rule,
            **metrics,
            **self._grasp(),
            "privileged": self._privileged,
        }
        return obs, info

    def step(self, action):
        a = self._begin_step(action)
        try:
            self.twin.step(self.state, a)
        except SimulationDiverged as err:
            return self._end_step(err)
        return self._end_step(None)

    def _begin_step(self, action) -> np.ndarray:
        """Check and clip the action, then count the step."""
        a = self._check_action(action)
        self._steps += 1
        return a

    def _check_action(self, action) -> np.ndarray:
        """The clipped action; raises (changing nothing) for a finished episode or a malformed action."""
        if self._status != "ok":
            raise RuntimeError(f"{self.rules.name}: the episode ended with a simulation error; call reset()")
        if self._done:
            raise RuntimeError(
                f"{self.rules.name}: the episode is over (terminated or truncated); call reset()"
            )
        try:
            a = np.asarray(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action: expected an array of shape {self.action_space.shape}, got "
                             f"{type(action).__name__}") from None
        if a.shape != self.action_space.shape:
            raise ValueError(f"action: expected shape {self.action_space.shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action: contains NaN or inf: {a}")
        return np.clip(a, self.action_space.low, self.action_space.high)

    def _end_step(self, error: SimulationDiverged | None, images: dict | None = None):
        """The step's (obs, reward, terminated, truncated, info) once the twin has advanced (`images`: the
        state's renders when the caller made them, as TwinVectorEnv does for all worlds at once)."""
        if error is not None:
            self._status = "sim_error"
            info = {
                "is_success": False,
                "status": "sim_error",
                "error": str(error),
                "success_rule": self.success_rule,
            }
            return self._last_obs, 0.0, True, False, info
        hit, metrics = self.rules.frame(self.twin, self.state)
        success = self._success.update(hit)
        obs = self._observe(metrics, images)
        terminated = success and self.success_rule == "early"
        truncated = self._steps >= self._max_episode_steps and not terminated
        self._done = terminated or truncated
        info = {
            "is_success": success,
            "status": "ok",
            "success_rule": self.success_rule,
            **metrics,
            **self._grasp(),
            "privileged": self._privileged,
        }
        return obs, self.rules.reward(metrics), terminated, truncated, info

    def _grasp(self) -> dict:
        status = self.twin.grasp_status(self.state)
        return {} if status is None else {"grasp": status}

    def render(self):
        if not self.render_views:
            raise RuntimeError("render(): this env observes no camera (cameras=''); make it with cameras=...")
        frames = [self._frames[v] for v in self.render_views]
        return frames[0] if len(frames) == 1 else np.concatenate(frames, axis=1)

    def _observe(self, metrics: dict, images: dict | None = None) -> dict:
        if images is None:
            images = self.twin.render(self.state, self.cameras) if self.cameras else {}
        outs = images
        frames = {name: out.rgb_uint8() for name, out in outs.items()}
        self.rules.decorate(frames)
        for name, response in self._responses.items():
            frames[name] = response.apply(frames[name], self._response_rngs[name])
        self._frames = frames
        self._privileged = self.rules.privileged(self.twin, self.state, metrics)
        obs = {"pixels": frames, "agent_pos": self.twin.ee_state(self.state).astype(np.float32)}
        robot, q = self.twin.robot, self.state.robot.q
        obs["joint_position"] = q[robot.arm_q_indices].astype(np.float32)
        if robot.gripper_joint is not None:
            closed = np.clip(robot.gripper_closedness(q), 0.0, 1.0)
            obs["gripper_position"] = np.array([closed], np.float32)
        depth = {name: outs[name].depth for name in self.cameras if self.twin.cameras[name].depth}
        if depth:
            obs["depth"] = depth
        if self.environment_state:
            obs["environment_state"] = self._privileged["environment_state"]
        self._last_obs = obs
        return obs


def _camera_list(cameras: str | None, twin) -> list[str]:
    """The `cameras` keyword ("front", "front+wrist"; "": none, for runs that need no images such as open-loop
    replays; None: every camera of the twin) as a list, checked."""
    names = list(twin.cameras)
    if cameras is None:
        return names
    if cameras == "":
        return []
    chosen = cameras.split("+") if isinstance(cameras, str) else []
    if not chosen or len(set(chosen)) != len(chosen) or any(c not in names for c in chosen):
        raise ValueError(f"cameras: expected distinct names from {names} joined by '+', got {cameras!r}")
    return chosen


def settle_worlds(twin, states: list, steps: int, worlds=None) -> None:
    """Advance the worlds `worlds` (indices; default all) of `twin` (`states`: all its world states, in
    order) `steps` frames with the robots held still, and refit their object poses. A frame steps every
    world: the other worlds' particles are put back as they were."""
    worlds = list(range(len(states))) if worlds is None else [int(w) for w in worlds]
    if steps <= 0 or not worlds:
        return
    physics = states[0].physics
    others = [s.world for s in states if s.world not in worlds]
    kept = (physics.x.numpy().copy(), physics.v.numpy().copy()) if others else None  # numpy(): a view on CPU
    for _ in range(steps):
        for w, result in enumerate(twin.step_worlds(states, [None] * len(states))):
            if w in worlds and isinstance(result, SimulationDiverged):
                raise result
    x = physics.x.numpy()
    if kept is not None:
        v = physics.v.numpy()
        for w in others:
            span = twin._span(states[w])
            x[span], v[span] = kept[0][span], kept[1][span]
        physics.x.assign(x)
        physics.v.assign(v)
    for w in worlds:
        twin._fit_poses(states[w], x)


class TwinVectorEnv(gymnasium.vector.VectorEnv):
    """`num_envs` worlds of one twin stepped together: one physics launch per kernel for all worlds, each
    world's episode bit-identical to the same episode in a `TwinEnv` (CPU).

        envs = gymnasium.make_vec("twinbench/PushT-v0", num_envs=16, vectorization_mode="vector_entry_point",
                                  preset="fast")
        obs, infos = envs.reset(seed=0, options={"init_state": list(range(16))})
        obs, rewards, terminated, truncated, infos = envs.step(actions)      # actions: (16, action_dim)

    Takes TwinEnv's keyword arguments. Autoreset follows gymnasium's NEXT_STEP mode: the step after a
    world's episode ends resets that world (its action is ignored, its robot held) as `TwinEnv.reset()`
    would. `reset(seed, options)`: `seed` an int (world i gets seed + i) or one per world; `options` as
    TwinEnv's, where `init_state` may be one index per world, plus `reset_mask` (bool per world) to reset
    only some worlds. A world that diverges ends its own episode with `info["status"] == "sim_error"`;
    the others go on. `envs.envs[i]` is world i's TwinEnv view (rules, twin, state).
    """

    metadata = {
        "render_modes": ["rgb_array"],
        "render_fps": 30,
        "autoreset_mode": gymnasium.vector.AutoresetMode.NEXT_STEP,
    }

    def __init__(
        self,
        task="push-t",
        num_envs: int = 1,
        *,
        twin=None,
        preset: str = "reference",
        device: str = "cpu",
        render_mode: str | None = "rgb_array",
        render_views: str | None = None,
        environment_state: bool = False,
        success_rule: str = "final",
        roles: dict | None = None,
        cameras: str | None = None,
        **settings,
    ):
        import copy

        from gymnasium.vector.utils import batch_space

        from twinbench.twin import build_twin

        if isinstance(num_envs, bool) or not isinstance(num_envs, int | np.integer) or num_envs < 1:
            raise ValueError(f"num_envs must be a positive integer, got {num_envs!r}")
        quiet_warp()
        rules, twin_spec = resolve_task_twin(task, twin, preset, roles, settings)
        self.twin, states = build_twin(twin_spec, device, num_worlds=int(num_envs))
        states = states if isinstance(states, list) else [states]
        args = (render_mode, render_views, environment_state, success_rule, cameras)
        self.envs = [
            TwinEnv._world(rules if i == 0 else copy.deepcopy(rules), self.twin, st, *args)
            for i, st in enumerate(states)
        ]
        for env in self.envs:
            env._worlds = states
        first = self.envs[0]
        self.num_envs = len(self.envs)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": first.metadata["render_fps"]}
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)
        self._autoreset = np.zeros(self.num_envs, dtype=bool)
        self._obs: list = [None] * self.num_envs

    def _per_world(self, name: str, value) -> list:
        if isinstance(value, list | tuple | np.ndarray):
            if len(value) != self.num_envs:
                raise ValueError(f"{name}: {len(value)} values for {self.num_envs} worlds")
            return list(value)
        return [value] * self.num_envs

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        options = check_reset_options(options)
        mask = np.asarray(options.pop("reset_mask", np.ones(self.num_envs, bool)), dtype=bool)
        if mask.shape != (self.num_envs,):
            raise ValueError(
                f"options['reset_mask']: expected {self.num_envs} booleans, got shape {mask.shape}"
            )
        if isinstance(seed, int | np.integer) and not isinstance(seed, bool):
            seeds = [int(seed) + i for i in range(self.num_envs)]
        else:
            seeds = self._per_world("seed", seed)
        per_world = {k: self._per_world(f"options[{k!r}]", v) for k, v in options.items()}
        infos: dict = {}
        chosen = np.flatnonzero(mask)
        for i in chosen:
            self.envs[i]._place(seeds[i], {k: v[i] for k, v in per_world.items()})
        settle_worlds(self.twin, self.envs[0]._worlds, self.envs[0].settle_steps, chosen)
        for i in chosen:
            self._obs[i], info = self.envs[i]._first_observation()
            self._autoreset[i] = False
            infos = self._add_info(infos, info, i)
        return self._batch(), infos

    def step(self, actions):
        actions = np.asarray(actions)
        if actions.shape != self.action_space.shape:
            raise ValueError(f"actions: expected shape {self.action_space.shape}, got {actions.shape}")
        for i, env in enumerate(self.envs):  # every action checked before any world moves
            if not self._autoreset[i]:
                env._check_action(actions[i])
        results = self.step_worlds([None if self._autoreset[i] else actions[i] for i in range(self.num_envs)])
        rewards = np.zeros(self.num_envs, dtype=np.float64)
        terminated = np.zeros(self.num_envs, dtype=bool)
        truncated = np.zeros(self.num_envs, dtype=bool)
        infos: dict = {}
        for i, env in enumerate(self.envs):
            if results[i] is None:  # NEXT_STEP autoreset of a world whose episode ended last step
                self._obs[i], info = env.reset()
            else:
                self._obs[i], rewards[i], terminated[i], truncated[i], info = results[i]
            self._autoreset[i] = terminated[i] or truncated[i]
            infos = self._add_info(infos, info, i)
        return self._batch(), rewards, terminated, truncated, infos

    def step_worlds(self, actions: list) -> list:
        """Step the worlds whose action is given and hold the others (None) in one physics frame, without
        autoreset: per world its TwinEnv-style (obs, reward, terminated, truncated, info), None when held,
        or the exception its action raised (that world held). For drivers that reset worlds themselves
        (`envs.envs[i].reset(...)`), such as the evaluation runner."""
        if len(actions) != self.num_envs:
            raise ValueError(f"step_worlds: {len(actions)} actions for {self.num_envs} worlds")
        clipped: list = []
        for env, action in zip(self.envs, actions, strict=True):
            try:
                clipped.append(None if action is None else env._begin_step(action))
            except Exception as err:  # noqa: BLE001 - reported as that world's result
                clipped.append(err)
        moves = [a if isinstance(a, np.ndarray) else None for a in clipped]
        results = self.twin.step_worlds([env.state for env in self.envs], moves)
        # the worlds that moved and are healthy: every camera of all of them rendered in one call
        shown = [
            i for i, r in enumerate(results) if moves[i] is not None and not isinstance(r, SimulationDiverged)
        ]
        states, cameras = [self.envs[i].state for i in shown], self.envs[0].cameras
        renders = self.twin.render_worlds(states, cameras) if cameras else [{} for _ in states]
        images = dict(zip(shown, renders, strict=True))
        out: list = []
        for i, (env, a, result) in enumerate(zip(self.envs, clipped, results, strict=True)):
            if a is None or isinstance(a, Exception):
                out.append(a)
            elif isinstance(result, SimulationDiverged):
                out.append(env._end_step(result))
            else:
                out.append(env._end_step(None, images[i]))
        return out

    def _batch(self):
        from gymnasium.vector.utils import concatenate, create_empty_array

        out = create_empty_array(self.single_observation_space, self.num_envs)
        return concatenate(self.single_observation_space, self._obs, out)

    def render(self):
        return tuple(env.render() for env in self.envs)
