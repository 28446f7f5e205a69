"""Task registry: every task names its Gymnasium env id, scripted expert and initial-state grid.

A task module registers itself on import (`register_task`); `get_task` imports the package's task
modules when asked for a name not registered yet. Tasks over a twin (`tasks.base.TwinTask`) run in the
generic `twinbench.env.TwinEnv`; the env ids are registered with gymnasium on `import twinbench`.
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


def register_task(name: str, *, env_id: str, make_expert: Callable[[Any], Any], n_grid_states: int,
                  description: str, task_cls: type | None = None) -> TaskSpec:
    """Register a task under `name` (re-registering the same name replaces it)."""
    if not name or not isinstance(name, str):
        raise ValueError(f"task name must be a non-empty string, got {name!r}")
    if int(n_grid_states) < 1:
        raise ValueError(f"task {name!r}: n_grid_states must be >= 1, got {n_grid_states}")
    if not callable(make_expert):
        raise ValueError(f"task {name!r}: make_expert must be callable (make_expert(env) -> policy)")
    spec = TaskSpec(name, env_id, make_expert, int(n_grid_states), description, task_cls)
    _TASKS[name] = spec
    return spec


def _discover() -> None:
    """Import every module of this package once, so tasks that register themselves on import (e.g.
    push-T) are found; an import error inside a task module propagates."""
    global _DISCOVERED
    if _DISCOVERED:
        return
    _DISCOVERED = True
    for info in pkgutil.iter_modules(__path__):
        importlib.import_module(f"{__name__}.{info.name}")


def get_task(name: str) -> TaskSpec:
    """The registered task `name`; ValueError listing the known tasks otherwise."""
    if name not in _TASKS:
        _discover()
    try:
        return _TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; known tasks: {sorted(_TASKS)}") from None


def task_names() -> list[str]:
    """Names of all registered tasks (every task module imported), sorted."""
    _discover()
    return sorted(_TASKS)


# The cheap debug task is registered on import; other task modules register when first asked for
# (`get_task` of an unknown name or `task_names`), so importing this package stays light.
_DISCOVERED = False
importlib.import_module(f"{__name__}.point_reach")
