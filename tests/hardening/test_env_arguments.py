"""Env keyword arguments, reset options and actions of the wrong type or range: a ValueError naming the
argument, before anything is built or moved (issue 25)."""

from __future__ import annotations

import gymnasium as gym
import pytest

import twinbench  # noqa: F401 - registers the env ids
from twinbench.cli import main as cli
from twinbench.env import TwinEnv, TwinVectorEnv


@pytest.mark.parametrize(("kw", "needle"), [
    ({"substeps": 0}, "substeps=0: expected an integer in [1, 100000]"),
    ({"substeps": -3}, "substeps=-3"),
    ({"substeps": 2.5}, "substeps=2.5"),
    ({"substeps": True}, "substeps=True"),
    ({"substeps": 10**9}, "substeps=1000000000"),
    ({"fps": 0.0}, "fps=0.0: expected a number in [1.0, 1000.0]"),
    ({"fps": float("nan")}, "fps=nan"),
    ({"fps": float("inf")}, "fps=inf"),
    ({"fps": "30"}, "fps='30'"),
    ({"episode_seconds": float("nan")}, "episode_seconds=nan: expected a number in [0.001, 86400.0]"),
    ({"settle_steps": -1}, "settle_steps=-1: expected an integer in [0, 100000]"),
    ({"success_window": 0}, "success_window=0: expected an integer in [1, 1000000]"),
    ({"pusher_start": [float("nan"), 0.0]}, "pusher_start=[nan, 0.0]: numbers must be finite"),
])
def test_out_of_range_settings_name_the_argument(kw, needle):
    with pytest.raises(ValueError) as err:
        gym.make("twinbench/PushT-v0", preset="fast", **kw)
    assert needle in str(err.value)
    with pytest.raises(ValueError, match=needle.split(":")[0].replace("[", r"\[")):
        TwinVectorEnv("push-t", 2, preset="fast", **kw)


def test_eval_env_kwargs_out_of_range_is_one_line_exit_2(tmp_path, capsys):
    assert cli(["eval", "--run-id", "r", "--task", "push-t", "--policy", "expert", "--episodes", "1",
                "--env-kwargs", '{"substeps": 0}', "--db", str(tmp_path / "r.sqlite"),
                "--output-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "substeps=0" in err[-1], err


@pytest.fixture(scope="module")
def env():
    e = TwinEnv("push-t", preset="fast")
    yield e
    e.close()


@pytest.mark.parametrize("options", [[("init_state", 1)], "init_state", 5, ("init_state",)])
def test_reset_options_of_the_wrong_type_name_the_argument(env, options):
    with pytest.raises(ValueError, match=r"reset\(options=\.\.\.\): expected a dict"):
        env.reset(options=options)
    obs, _ = env.reset(options={"init_state": 1})  # the env still works
    assert obs["agent_pos"].shape == (2,)


@pytest.mark.parametrize("action", [{"x": 1.0, "y": 0.0}, "left", object()])
def test_an_action_of_the_wrong_type_names_the_argument(env, action):
    obs, _ = env.reset(seed=0)
    with pytest.raises(ValueError, match=r"action: expected an array of shape \(2,\), got"):
        env.step(action)
    obs, *_ = env.step(obs["agent_pos"])  # nothing moved or counted: the env still steps
    assert obs["agent_pos"].shape == (2,) and env._steps == 1
