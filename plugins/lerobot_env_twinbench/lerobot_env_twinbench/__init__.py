"""LeRobot env plugin for twinbench: `--env.type=twinbench` runs any twinbench task with LeRobot's own loop.

    lerobot-eval --policy.path=DIR --env.type=twinbench --env.task=PushT-v0 \
        --env.preset=fast --eval.n_episodes=4 --eval.batch_size=2 --eval.use_async_envs=true

LeRobot (0.6) imports every installed distribution whose name starts with `lerobot_env_`; importing this
one registers `TwinbenchEnv` as the env type `twinbench` (and twinbench's gymnasium ids).

- `--env.task`: an env id (`PushT-v0`, `PointReach-v0`, with or without `twinbench/`) or a task name
  (`push-t`, `point-reach`).
- `--env.preset`, `--env.twin` (a twin directory), `--env.render_views`, `--env.episode_seconds` and
  `--env.env_kwargs` (a JSON object, as `twinbench eval --env-kwargs`) go to the env's constructor.
- Episode k of a run starts from grid state `seed mod n_grid` (LeRobot seeds episode k with
  `--seed + k`); the env's `task` / `task_description` is the prompt LeRobot's loop gives the policy.
- `features` (the policy's inputs and outputs: `pixels/<camera>` -> `observation.images.<camera>`,
  `agent_pos` -> `observation.state`, `environment_state` -> `observation.environment_state`) are
  declared by the config itself, from the task and its twin's description (cameras, action mode) without
  making an env, as LeRobot's own env configs do: `make_policy(cfg, env_cfg=...)` works before any env
  exists. A task with its own env class (not a TwinEnv) makes one env once to read them. `create_envs`
  checks them against the envs' spaces.
- `--env.disable_env_checker=false` runs gymnasium's env checker on each sub-env (LeRobot's default:
  true, skipped).
- Sub-envs are made by `make_env` (a module-level function, so a forkserver worker of an
  `AsyncVectorEnv` imports twinbench, and with it the env ids, before `gymnasium.make`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from functools import partial

import gymnasium as gym
from lerobot.configs import FeatureType, PolicyFeature
from lerobot.envs.configs import EnvConfig
from lerobot.utils.constants import ACTION, OBS_ENV_STATE, OBS_IMAGES, OBS_STATE

import twinbench

__all__ = ["TwinbenchEnv", "make_env", "resolve_env_id"]

# The reset option LeRobot's rollout passes to every sub-env (lerobot.envs.utils.NEW_ROLLOUT_OPTION).
LEROBOT_RESET_OPTIONS = ("lerobot_new_rollout",)


def resolve_env_id(task: str) -> str:
    """`PushT-v0` | `twinbench/PushT-v0` | `push-t` -> the gymnasium id `twinbench/PushT-v0`."""
    if not task:
        raise ValueError(
            f"--env.task: give a twinbench env id or task name; env ids: {sorted(twinbench.ENV_IDS)}"
        )
    env_id = task if task.startswith("twinbench/") else f"twinbench/{task}"
    if env_id in twinbench.ENV_IDS:
        return env_id
    from twinbench.tasks import get_task, task_names

    try:
        return get_task(task).env_id
    except ValueError:
        raise ValueError(
            f"--env.task={task!r}: not a twinbench env id or task; env ids: "
            f"{sorted(i.split('/', 1)[1] for i in twinbench.ENV_IDS)}, tasks: {task_names()}"
        ) from None


class LeRobotResetOptions(gym.Wrapper):
    """Drops LeRobot's own reset options, which twinbench envs would reject as unknown."""

    def reset(self, *, seed=None, options=None):
        options = {k: v for k, v in (options or {}).items() if k not in LEROBOT_RESET_OPTIONS}
        return self.env.reset(seed=seed, options=options or None)


def make_env(env_id: str, kwargs: dict, disable_env_checker: bool = True) -> gym.Env:
    """One sub-env; importing twinbench here registers its ids in any (spawned) worker process."""
    import twinbench  # noqa: F401 - registers the env ids
    from twinbench._runtime import quiet_warp

    quiet_warp()  # no Warp banner or per-module load lines in LeRobot's output
    return LeRobotResetOptions(gym.make(env_id, disable_env_checker=disable_env_checker, **kwargs))


# TwinEnv's own keyword arguments; the others are the task's or the cell's settings
_ENV_ARGS = ("twin", "preset", "device", "render_mode", "render_views", "environment_state", "success_rule",
             "roles")


def declared_spaces(env_id: str, kwargs: dict) -> tuple[gym.spaces.Dict, gym.spaces.Box, int]:
    """(observation space, action space, fps) of the env `gym.make(env_id, **kwargs)` would make, read from
    the task and its twin's description (TwinEnv tasks: no twin is built), else from one env made here."""
    import numpy as np

    from twinbench.env import resolve_task_twin
    from twinbench.tasks import get_task, task_names

    task = next((get_task(n) for n in task_names() if get_task(n).env_id == env_id), None)
    if task is None or task.task_cls is None:
        env = make_env(env_id, kwargs)
        try:
            return env.observation_space, env.action_space, int(env.metadata["render_fps"])
        finally:
            env.close()
    defaults = gym.spec(env_id).kwargs
    args = {**defaults, **kwargs}
    settings = {k: v for k, v in args.items() if k not in (*_ENV_ARGS, "task")}
    rules, twin = resolve_task_twin(args.get("task", task.name), args.get("twin"),
                                    args.get("preset", "reference"), args.get("roles"), settings)
    ctrl = twin.controller
    state_dim = 2 if ctrl.action_mode == "planar" else 8
    obs = {"pixels": gym.spaces.Dict({c.name: gym.spaces.Box(0, 255, (*c.output_hw, 3), np.uint8)
                                      for c in twin.cameras}),
           "agent_pos": gym.spaces.Box(-np.inf, np.inf, (state_dim,), np.float32)}
    if args.get("environment_state"):
        obs["environment_state"] = gym.spaces.Box(-np.inf, np.inf, (rules.environment_state_dim,), np.float32)
    action = gym.spaces.Box(-np.inf, np.inf, (ctrl.action_dim,), np.float32)
    return gym.spaces.Dict(obs), action, int(round(ctrl.control_hz))


def features_from_spaces(observation_space: gym.spaces.Dict, action_space: gym.spaces.Box
                         ) -> tuple[dict[str, PolicyFeature], dict[str, str]]:
    """LeRobot `features` and `features_map` of a twinbench env's spaces."""
    features = {ACTION: PolicyFeature(type=FeatureType.ACTION, shape=tuple(action_space.shape))}
    fmap = {ACTION: ACTION}
    for cam, space in observation_space["pixels"].spaces.items():
        features[f"pixels/{cam}"] = PolicyFeature(type=FeatureType.VISUAL, shape=tuple(space.shape))
        fmap[f"pixels/{cam}"] = f"{OBS_IMAGES}.{cam}"
    state_shape = tuple(observation_space["agent_pos"].shape)
    features["agent_pos"] = PolicyFeature(type=FeatureType.STATE, shape=state_shape)
    fmap["agent_pos"] = OBS_STATE
    if "environment_state" in observation_space.spaces:
        shape = tuple(observation_space["environment_state"].shape)
        features["environment_state"] = PolicyFeature(type=FeatureType.ENV, shape=shape)
        fmap["environment_state"] = OBS_ENV_STATE
    return features, fmap


@EnvConfig.register_subclass("twinbench")
@dataclass
class TwinbenchEnv(EnvConfig):
    """`--env.type=twinbench`: a twinbench task (see the module docstring)."""

    task: str | None = "PushT-v0"
    fps: int = 30
    preset: str | None = None  # built-in cell preset ("reference" | "fast"); None: the env's default
    twin: str | None = None  # a twin directory (TwinEnv tasks)
    render_views: str | None = None  # cameras side by side in the videos, e.g. "front+wrist"
    episode_seconds: float | None = None
    env_kwargs: str = "{}"  # JSON object of further constructor arguments
    features: dict[str, PolicyFeature] = field(default_factory=dict)
    features_map: dict[str, str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.env_id = resolve_env_id(self.task or "")
        try:
            extra = json.loads(self.env_kwargs or "{}")
        except json.JSONDecodeError as err:
            raise ValueError(
                f"--env.env_kwargs: not valid JSON ({err}); e.g. '{{\"preset\": \"fast\"}}'"
            ) from None
        if not isinstance(extra, dict):
            raise ValueError(f"--env.env_kwargs: expected a JSON object, got {type(extra).__name__}")
        self._extra_kwargs = extra
        if not self.features:  # declared from the task, as LeRobot's own env configs do
            obs, action, self.fps = declared_spaces(self.env_id, self.gym_kwargs)
            self.features, self.features_map = features_from_spaces(obs, action)

    @property
    def package_name(self) -> str:
        return "twinbench"

    @property
    def gym_id(self) -> str:
        return self.env_id

    @property
    def gym_kwargs(self) -> dict:
        named = {"preset": self.preset, "twin": self.twin, "render_views": self.render_views,
                 "episode_seconds": self.episode_seconds}
        return {**{k: v for k, v in named.items() if v is not None}, **self._extra_kwargs}

    def create_envs(
        self, n_envs: int, use_async_envs: bool = False
    ) -> dict[str, dict[int, gym.vector.VectorEnv]]:
        """`{"twinbench": {0: VectorEnv}}` of `n_envs` sub-envs (async: forkserver workers)."""
        make = partial(make_env, self.env_id, self.gym_kwargs, self.disable_env_checker)
        fns = [make] * n_envs
        mode = gym.vector.AutoresetMode.SAME_STEP
        if use_async_envs and n_envs > 1:
            vec = gym.vector.AsyncVectorEnv(fns, context="forkserver", autoreset_mode=mode)
        else:
            vec = gym.vector.SyncVectorEnv(fns, autoreset_mode=mode)
        features, features_map = features_from_spaces(vec.single_observation_space, vec.single_action_space)
        fps = int(vec.metadata["render_fps"])
        if (features, features_map, fps) != (self.features, self.features_map, self.fps):
            vec.close()
            raise ValueError(f"--env.task={self.task}: the envs' features {features} at {fps} fps differ "
                             f"from the config's {self.features} at {self.fps} fps")
        return {self.type: {0: vec}}
