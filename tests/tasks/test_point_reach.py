"""The point-reach debug task: env contract, analytic grid states and motion, forced failures."""

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import twinbench.tasks.point_reach as pr
from twinbench.errors import SimulationDiverged
from twinbench.tasks import get_task, task_names


def test_registry_and_env_checker():
    task = get_task("point-reach")
    assert task.env_id == "twinbench/PointReach-v0" and task.n_grid_states == 8
    env = task.make_env()
    check_env(env.unwrapped, skip_render_check=False)
    assert env.unwrapped._max_episode_steps == 60 and env.unwrapped.metadata["render_fps"] == 10
    assert isinstance(env.unwrapped.task_description, str)
    with pytest.raises(ValueError, match="point-reach"):
        get_task("no-such-task")
    assert "point-reach" in task_names()


def test_grid_states_sampled_states_and_observation():
    env = get_task("point-reach").make_env()
    for i in range(8):
        obs, info = env.reset(seed=0, options={"init_state": i})
        a = 2 * np.pi * i / 8
        np.testing.assert_allclose(obs["agent_pos"], [0.18 * np.cos(a), 0.18 * np.sin(a)], atol=1e-6)
        assert info == {"is_success": False, "status": "ok"}
    assert obs["pixels"]["front"].shape == (64, 64, 3) and obs["pixels"]["front"].dtype == np.uint8
    assert obs["pixels"]["wrist"].shape == (64, 64, 3)
    # the agent is drawn red at its position (state 0: x = +0.18, y = 0 -> column 55, row 32)
    obs, _ = env.reset(seed=0, options={"init_state": 0})
    assert tuple(obs["pixels"]["front"][32, 55]) == (220, 30, 30)
    # goal disk at the centre: grey 200 blended half-and-half with yellow (255, 220, 0); background grey
    assert tuple(obs["pixels"]["front"][32, 32]) == (227, 210, 100)
    assert tuple(obs["pixels"]["front"][0, 0]) == (200, 200, 200)
    assert (obs["pixels"]["front"] == (227, 210, 100)).all(axis=2).sum() > 40  # the disk, not one pixel
    assert np.array_equal(env.render(), obs["pixels"]["front"])
    s1 = env.reset(seed=5, options={"init_state": 8})[0]["agent_pos"]
    s2 = env.reset(seed=5, options={"sampled": True})[0]["agent_pos"]
    s3 = env.reset(seed=6, options={"init_state": 9})[0]["agent_pos"]
    assert np.array_equal(s1, s2) and not np.array_equal(s1, s3)
    assert np.linalg.norm(s1) > 0.08 and np.all(np.abs(s1) <= 0.25)


def test_rate_limited_motion_and_expert_episode_length():
    env = get_task("point-reach").make_env()
    obs, _ = env.reset(seed=0, options={"init_state": 2})  # (0, 0.18)
    obs, *_ = env.step(np.array([0.0, -0.25], np.float32))
    np.testing.assert_allclose(obs["agent_pos"], [0.0, 0.16], atol=1e-6)  # moved exactly MAX_STEP
    obs, *_ = env.step(np.array([0.0, 0.165], np.float32))  # target closer than MAX_STEP: reached
    np.testing.assert_allclose(obs["agent_pos"], [0.0, 0.165], atol=1e-6)
    # expert from the grid: 0.18 m at 0.02 m/step enters the 0.03 m disk at step 8, holds 5 steps -> 12
    expert = get_task("point-reach").make_expert(env)
    for i in range(8):
        obs, _ = env.reset(seed=0, options={"init_state": i})
        steps, term, trunc = 0, False, False
        while not (term or trunc):
            obs, r, term, trunc, info = env.step(expert.select_action(obs))
            steps += 1
        assert (steps, info["is_success"], term) == (12, True, True)
        assert r == pytest.approx(1.0)


def test_time_limit_and_forced_failures():
    env = get_task("point-reach").make_env()
    env.reset(seed=0, options={"init_state": 0})
    for _ in range(60):
        *_, term, trunc, info = env.step(np.array([0.2, 0.2], np.float32))  # never at the goal
    assert (term, trunc, info["is_success"]) == (False, True, False)
    env = get_task("point-reach").make_env(fail_mode="nan", fail_step=3)
    env.reset(seed=0)
    statuses = [env.step(np.zeros(2, np.float32))[4]["status"] for _ in range(3)]
    assert statuses == ["ok", "ok", "sim_error"]
    env = get_task("point-reach").make_env(fail_mode="raise", fail_step=1)
    env.reset(seed=0)
    with pytest.raises(SimulationDiverged):
        env.step(np.zeros(2, np.float32))
    with pytest.raises(ValueError, match="fail_mode"):
        pr.PointReachEnv(fail_mode="bogus")
