"""twinbench: evaluate robot manipulation policies in photorealistic digital twins.

Importing twinbench registers the gymnasium env id of every declared task (`twinbench.tasks`: the task
modules are imported, which is light, NumPy and gymnasium; Warp loads when an env is made). An installed
twinbench also registers them whenever gymnasium is imported (the `twinbench-gym.pth` startup hook, see
`_twinbench_gym_hook`; off with TWINBENCH_NO_GYM_HOOK=1), so `gymnasium.make("twinbench/PushT-v0")` works
in any interpreter without `import twinbench`.
"""

__version__ = "0.1.0"


def register_envs() -> None:
    """Register the env ids of twinbench's tasks with gymnasium (idempotent)."""
    from twinbench.tasks import discover

    discover()


def env_ids() -> list[str]:
    """The gymnasium env ids of the registered tasks, sorted."""
    from twinbench.tasks import get_task, task_names

    return sorted({get_task(name).env_id for name in task_names()})


def __getattr__(name: str):
    if name == "ENV_IDS":  # the env ids as a tuple (older name, kept for callers such as the LeRobot plugin)
        return tuple(env_ids())
    raise AttributeError(f"module 'twinbench' has no attribute {name!r}")


register_envs()
