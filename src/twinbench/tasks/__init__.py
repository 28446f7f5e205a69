"""Task registry: every task is declared once, by `register_task` at the end of its module, which also
registers its Gymnasium env id.

A task over a twin declares a `tasks.base.TwinTask` subclass (class attributes `name`, `env_id`,
`description`; its initial-state grid; its rules) and calls `register_task(MyTask, make_expert=...)`: the
grid size is `len(MyTask().initial_states)` and the env is the generic `twinbench.env.TwinEnv`. A task
with its own env class (point-reach) gives its entry point and grid size instead. `import twinbench`
imports this package's task modules (light: NumPy and gymnasium; Warp loads when an env is made), so
their ids are registered; a task module of your own registers its id when you import it.
Env conventions every task follows:

- `reset(seed=s, options={"init_state": i})` starts from grid state i (0 <= i < n_grid_states); a
  state sampled from the task's sampler (seeded by `seed`) for i >= n_grid_states or
  `options={"sampled": True}`; without `init_state`, grid state `seed mod n_grid_states` (0 without a
  seed).
- observation `{"pixels": {"front": HxWx3 uint8, "wrist": HxWx3 uint8}, "agent_pos": float32}`.
- `step` returns `(obs, reward, terminated, truncated, info)` with `info["is_success"]` (bool) and
  `info["status"]` in {"ok", "sim_error"} on every step; an env may instead raise
  `twinbench.errors.SimulationDiverged`.
- `render()` returns the front frame; attributes `task_description`, `_max_episode_steps` and
  `metadata["render_fps"]`.
"""

from __future__ import annotations

import importlib
import pkgutil
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from twinbench.errors import InputError

TWIN_ENV, TWIN_VECTOR_ENV = "twinbench.env:TwinEnv", "twinbench.env:TwinVectorEnv"


@dataclass(frozen=True)
class TaskSpec:
    """A registered task: its env id, how to build its scripted expert, and its grid size."""

    name: str
    env_id: str
    make_expert: Callable[[Any], Any]  # make_expert(env) -> policy with reset() / select_action(obs)
    n_grid_states: int
    description: str
    task_cls: type | None = None  # a tasks.base.TwinTask subclass (None: the task has its own env class)

    def make_env(self, **kwargs):
        """`gymnasium.make(env_id, **kwargs)` (env-checker wrapper off: the runner validates outputs)."""
        import gymnasium

        return gymnasium.make(self.env_id, disable_env_checker=True, **kwargs)

    def make_vector_env(self, num_envs: int, **kwargs):
        """`num_envs` worlds of the task's twin in one TwinVectorEnv (twin tasks only)."""
        if self.task_cls is None:
            raise InputError(f"task {self.name!r} has its own env ({self.env_id}), not a twin: it cannot run "
                             "several worlds in one env; use --worlds 1")
        import gymnasium

        return gymnasium.make_vec(self.env_id, num_envs=num_envs, vectorization_mode="vector_entry_point",
                                  **kwargs)


_TASKS: dict[str, TaskSpec] = {}


def register_task(task, *, make_expert: Callable[[Any], Any], env_id: str | None = None,
                  n_grid_states: int | None = None, description: str | None = None,
                  entry_point: str | None = None, max_episode_steps: int | None = None) -> TaskSpec:
    """Declare a task and register its env id with gymnasium (re-declaring a name replaces it).

    - A task over a twin: `register_task(MyTask, make_expert=make_expert)`; its name, env id and
      description are `MyTask`'s class attributes, its grid size `len(MyTask().initial_states)`, its env
      `twinbench.env.TwinEnv(task=name)` (and TwinVectorEnv).
    - A task with its own env class: `register_task(name, env_id=..., entry_point="module:Class",
      n_grid_states=..., description=..., make_expert=..., max_episode_steps=...)`; without `entry_point`
      the env id must already be registered with gymnasium.

    `make_expert(env) -> policy` builds the scripted expert (import the expert's module inside it).
    """
    if isinstance(task, type):
        args = {"env_id": env_id, "n_grid_states": n_grid_states, "description": description,
                "entry_point": entry_point}
        given = sorted(k for k, v in args.items() if v is not None)
        if given:
            raise ValueError(f"register_task({task.__name__}): {given} come from the task class "
                             "(class attributes and its initial_states), not from arguments")
        name, env_id, description = task.name, task.env_id, task.description
        n_grid_states = len(task().initial_states)
        entry_point, task_cls = TWIN_ENV, task
    else:
        name, task_cls = task, None
    if not name or not isinstance(name, str):
        raise ValueError(f"task name must be a non-empty string, got {name!r}")
    if not isinstance(env_id, str) or "/" not in env_id:
        raise ValueError(f"task {name!r}: env_id must be a gymnasium id 'namespace/Name-vN', got {env_id!r}")
    if n_grid_states is None or int(n_grid_states) < 1:
        raise ValueError(f"task {name!r}: the initial-state grid must have >= 1 state, got {n_grid_states}")
    if not callable(make_expert):
        raise ValueError(f"task {name!r}: make_expert must be callable (make_expert(env) -> policy)")
    spec = TaskSpec(name, env_id, make_expert, int(n_grid_states), description or "", task_cls)
    _TASKS[name] = spec
    if entry_point is not None:
        _register_env(env_id, entry_point, {"task": name} if task_cls else {}, max_episode_steps)
    return spec


def _register_env(env_id: str, entry_point: str, kwargs: dict, max_episode_steps: int | None) -> None:
    import gymnasium

    if env_id not in gymnasium.registry:
        vector = TWIN_VECTOR_ENV if entry_point == TWIN_ENV else None
        gymnasium.register(id=env_id, entry_point=entry_point, vector_entry_point=vector, kwargs=kwargs,
                           max_episode_steps=max_episode_steps)


def discover() -> None:
    """Import every module of this package once, so that its tasks are declared (and their env ids
    registered); an import error inside a task module propagates."""
    global _DISCOVERED
    if _DISCOVERED:
        return
    _DISCOVERED = True
    for info in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{info.name}")


def get_task(name: str) -> TaskSpec:
    """The registered task `name`; ValueError listing the known tasks otherwise."""
    if name not in _TASKS:
        discover()
    try:
        return _TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; known tasks: {sorted(_TASKS)}") from None


def task_names() -> list[str]:
    """Names of all registered tasks (every task module imported), sorted."""
    discover()
    return sorted(_TASKS)


_DISCOVERED = False
