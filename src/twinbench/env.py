"""TwinEnv: one gymnasium env for every task over a twin (a built-in cell or a twin directory).

    env = gymnasium.make("twinbench/PushT-v0", preset="fast")               # the task's built-in cell
    env = gymnasium.make("twinbench/PushT-v0", twin="path/to/twin_dir")     # your twin, same rules
    obs, info = env.reset(seed=0, options={"init_state": 3})

Observation: `{"pixels": {camera: HxWx3 uint8}, "agent_pos": float32}` (+ `"depth": {camera: HxW float32}`
for cameras with depth, + `"environment_state"` when made with `environment_state=True`). `info` holds
`is_success`, `status` ("ok" | "sim_error"), the task's metrics, `grasp` for a gripper ("holding",
"closed_on_air", "closing", "open") and `privileged` (object poses and the task's `environment_state`
vector, for scripted experts and offline rescoring).

Success rules (`success_rule`, recorded in `info["success_rule"]` and by the evaluation store):
- "final" (default, the reference study's rule): every episode runs its full length; the outcome is the
  task's window criterion (e.g. > 30 hits in the last 100 frames) at the final frame. `info["is_success"]`
  on each step tells whether the criterion holds over the frames so far.
- "early": the episode terminates as soon as the window criterion holds (a speed option).

Keyword arguments: `task` (registered name or a TwinTask), `twin` (directory or TwinSpec; default: the
task's built-in cell at `preset`), `device`, `success_rule`, `render_views` ("front", "front+wrist", ...:
the cameras `render()` puts side by side; default the first camera), `environment_state`, `roles`
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

from twinbench.physics import SimulationDiverged
from twinbench.tasks.base import SuccessWindow

RESET_OPTIONS = ("init_state", "sampled")
SUCCESS_RULES = ("final", "early")


def _split_settings(task_cls, settings: dict) -> tuple[dict, dict]:
    names = {f.name for f in dataclasses.fields(task_cls.settings_cls)}
    return {k: v for k, v in settings.items() if k in names}, {
        k: v for k, v in settings.items() if k not in names
    }


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
        **settings,
    ):
        from twinbench.tasks import get_task
        from twinbench.twin import TwinSpec, build_twin, load_twin

        if success_rule not in SUCCESS_RULES:
            raise ValueError(f"success_rule must be one of {SUCCESS_RULES}, got {success_rule!r}")
        self.success_rule = success_rule

        if isinstance(task, str):
            spec = get_task(task)
            if spec.task_cls is None:
                raise ValueError(f"task {task!r} has its own env ({spec.env_id}), not a TwinEnv")
            task_cls = spec.task_cls
        else:
            task_cls = type(task)
        task_settings, cell_settings = _split_settings(task_cls, settings)
        self.rules = task if not isinstance(task, str) else task_cls(roles, **task_settings)
        if twin is None:
            twin_spec = self.rules.default_twin(preset, **cell_settings)
        else:
            if cell_settings:
                raise ValueError(
                    f"unknown setting(s) {sorted(cell_settings)} for task {self.rules.name!r} "
                    f"with a twin from disk; task settings: "
                    f"{sorted(f.name for f in dataclasses.fields(task_cls.settings_cls))}"
                )
            twin_spec = twin if isinstance(twin, TwinSpec) else load_twin(Path(twin))
        overrides = self.rules.controller_overrides()
        if overrides:
            twin_spec = replace(twin_spec, controller=replace(twin_spec.controller, **overrides))
        self.twin, self.state = build_twin(twin_spec, device)
        self.rules.setup(self.twin, self.state)

        self.render_mode = render_mode
        views = render_views or next(iter(self.twin.cameras))
        self.render_views = views.split("+")
        unknown = [v for v in self.render_views if v not in self.twin.cameras]
        if unknown:
            raise ValueError(f"render_views: unknown camera(s) {unknown}; cameras: {list(self.twin.cameras)}")
        fps = int(round(self.twin.controller.config.control_hz))
        self.metadata = {**self.metadata, "render_fps": fps}
        self._max_episode_steps = int(round(self.rules.settings.episode_seconds * fps))
        self.task_description = self.task = self.rules.description  # `task`: the name LeRobot's loop reads
        self.environment_state = bool(environment_state)

        low, high = self.rules.action_bounds(self.twin)
        self.action_space = spaces.Box(low, high, dtype=np.float32)
        pixels, depth = {}, {}
        for name, cam in self.twin.cameras.items():
            h, w = cam.output_hw
            pixels[name] = spaces.Box(0, 255, (h, w, 3), np.uint8)
            if cam.depth:
                depth[name] = spaces.Box(0.0, np.inf, (h, w), np.float32)
        obs_space = {"pixels": spaces.Dict(pixels), "agent_pos": spaces.Box(low, high, dtype=np.float32)}
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
        super().reset(seed=seed)
        options = dict(options or {})
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
        self.rules.reset(self.twin, self.state, offsets)
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
        if self._status != "ok":
            raise RuntimeError(f"{self.rules.name}: the episode ended with a simulation error; call reset()")
        if self._done:
            raise RuntimeError(
                f"{self.rules.name}: the episode is over (terminated or truncated); call reset()"
            )
        a = np.asarray(action, dtype=np.float64)
        if a.shape != self.action_space.shape:
            raise ValueError(f"action: expected shape {self.action_space.shape}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action: contains NaN or inf: {a}")
        a = np.clip(a, self.action_space.low, self.action_space.high)
        self._steps += 1
        try:
            self.twin.step(self.state, a)
        except SimulationDiverged as err:
            self._status = "sim_error"
            info = {
                "is_success": False,
                "status": "sim_error",
                "error": str(err),
                "success_rule": self.success_rule,
            }
            return self._last_obs, 0.0, True, False, info
        hit, metrics = self.rules.frame(self.twin, self.state)
        success = self._success.update(hit)
        obs = self._observe(metrics)
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
        frames = [self._frames[v] for v in self.render_views]
        return frames[0] if len(frames) == 1 else np.concatenate(frames, axis=1)

    def _observe(self, metrics: dict) -> dict:
        outs = self.twin.render(self.state)
        frames = {name: out.rgb_uint8() for name, out in outs.items()}
        self.rules.decorate(frames)
        self._frames = frames
        self._privileged = self.rules.privileged(self.twin, self.state, metrics)
        obs = {"pixels": frames, "agent_pos": self.twin.ee_state(self.state).astype(np.float32)}
        depth = {name: outs[name].depth for name, cam in self.twin.cameras.items() if cam.depth}
        if depth:
            obs["depth"] = depth
        if self.environment_state:
            obs["environment_state"] = self._privileged["environment_state"]
        self._last_obs = obs
        return obs
