"""The task registry: every task is declared once (its class or its env), which yields its gymnasium id,
its grid size (from the grid itself) and its expert."""

import os
import subprocess
import sys

import gymnasium
import numpy as np
import pytest

import twinbench
from twinbench.tasks import _TASKS, get_task, register_task, task_names
from twinbench.tasks.base import InitialStates
from twinbench.tasks.push_t import PushTTask, make_expert


@pytest.mark.parametrize("name", task_names())
def test_every_declared_task_has_an_env_id_an_expert_and_a_grid(name):
    task = get_task(name)
    assert gymnasium.registry[task.env_id].entry_point  # registered with gymnasium
    assert task.env_id in twinbench.env_ids() and task.env_id in twinbench.ENV_IDS
    assert task.n_grid_states >= 1 and task.description
    kwargs = {"preset": "fast"} if task.task_cls is not None else {}
    env = task.make_env(**kwargs)
    try:
        if task.task_cls is not None:  # the grid size is the grid's: the class's and the env's
            assert len(task.task_cls().initial_states) == task.n_grid_states
            assert len(env.unwrapped.rules.initial_states) == task.n_grid_states
            assert type(env.unwrapped.rules) is task.task_cls and task.task_cls.env_id == task.env_id
        obs, info = env.reset(seed=0, options={"init_state": task.n_grid_states - 1})
        expert = task.make_expert(env)
        expert.reset()
        if getattr(expert, "uses_environment_state", False):
            obs = {**obs, "environment_state": info["privileged"]["environment_state"]}
        action = expert.select_action(obs)
        assert env.action_space.contains(np.asarray(action, env.action_space.dtype))
    finally:
        env.close()


def test_the_builtin_tasks_are_declared():
    assert task_names() == ["point-reach", "push-t", "rope-routing", "toy-packing"]
    assert [get_task(n).n_grid_states for n in task_names()] == [8, 16, 27, 20]


def test_a_new_task_class_is_one_declaration():
    class SmallGridPushT(PushTTask):
        name = "push-t-small-grid"
        env_id = "twinbench-test/SmallGridPushT-v0"
        description = "push-T from two states"

        def __init__(self, roles=None, **settings):
            super().__init__(roles, **settings)
            g = self.initial_states
            self.initial_states = InitialStates({"block": g.grid["block"][:2]}, g.low, g.high)

    try:
        spec = register_task(SmallGridPushT, make_expert=make_expert)
        assert get_task("push-t-small-grid") is spec and spec.n_grid_states == 2
        assert spec.task_cls is SmallGridPushT and spec.description == "push-T from two states"
        entry = gymnasium.registry["twinbench-test/SmallGridPushT-v0"]
        assert entry.entry_point == "twinbench.env:TwinEnv" and entry.kwargs == {"task": "push-t-small-grid"}
        assert entry.vector_entry_point == "twinbench.env:TwinVectorEnv"
        with pytest.raises(ValueError, match="come from the task class"):
            register_task(SmallGridPushT, make_expert=make_expert, n_grid_states=5)
    finally:
        _TASKS.pop("push-t-small-grid", None)
        gymnasium.registry.pop("twinbench-test/SmallGridPushT-v0", None)


def test_bad_declarations_are_refused():
    class NoId(PushTTask):
        name, env_id = "no-id", ""

    with pytest.raises(ValueError, match="env_id"):
        register_task(NoId, make_expert=make_expert)
    with pytest.raises(ValueError, match="make_expert"):
        register_task(PushTTask, make_expert=None)
    with pytest.raises(ValueError, match="grid"):
        register_task("x", env_id="twinbench/PointReach-v0", make_expert=make_expert, n_grid_states=0)
    assert "no-id" not in _TASKS and "x" not in _TASKS


def test_import_twinbench_registers_the_declared_ids_and_stays_light():
    """The ids come from the declarations (the task modules are imported), yet neither Warp nor the twin
    layer nor any renderer is imported."""
    code = (
        "import sys, twinbench, gymnasium\n"
        "from twinbench.tasks import _TASKS\n"
        "print(sorted(t.env_id for t in _TASKS.values()) == sorted(k for k in gymnasium.registry "
        "if k.startswith('twinbench/')), len(_TASKS))\n"
        "print(sorted(m for m in ('warp', 'trimesh', 'matplotlib', 'torch', 'twinbench.twin', "
        "'twinbench.physics', 'twinbench.env') if m in sys.modules))"
    )
    env = {k: v for k, v in os.environ.items() if not k.startswith("TWINBENCH_")}
    out = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True,
                         env={**env, "TWINBENCH_NO_GYM_HOOK": "1"}, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.split("\n")[:2] == ["True 4", "[]"]
