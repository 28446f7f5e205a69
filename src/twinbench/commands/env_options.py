"""The `--env-kwargs JSON` and `--twin DIR` options that `eval`, `replay` and `serve` share."""

from __future__ import annotations

import json
from pathlib import Path


def parse_env_kwargs(text: str) -> dict:
    """The `--env-kwargs` option: a JSON object of extra gymnasium.make keyword arguments ("" = none)."""
    try:
        env_kwargs = json.loads(text) if text else {}
    except json.JSONDecodeError as err:
        raise ValueError(f"--env-kwargs must be a JSON object, e.g. '{{\"step_delay_s\": 0.01}}': "
                         f"{err}") from err
    if not isinstance(env_kwargs, dict):
        raise ValueError("--env-kwargs must be a JSON object (dict)")
    return env_kwargs


def env_kwargs_with_twin(env_kwargs: dict, twin: Path | None, task: str) -> dict:
    """`--twin DIR`: evaluate `task` in the twin directory DIR (an absolute path, so worker processes find
    it); a task with an env of its own (point-reach) is refused."""
    if twin is None:
        return env_kwargs
    from twinbench.errors import InputError
    from twinbench.tasks import get_task

    if get_task(task).task_cls is None:
        raise InputError(f"--twin: task {task!r} has an env of its own, not a twin; run it without --twin")
    if "twin" in env_kwargs:
        raise ValueError("give the twin either as --twin or in --env-kwargs, not both")
    if not (Path(twin) / "twin.json").is_file():
        raise ValueError(f"--twin {twin}: no twin.json there (write one with `twinbench twin export` "
                         "or the construction tools)")
    return {**env_kwargs, "twin": str(Path(twin).resolve())}
