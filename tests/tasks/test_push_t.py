"""Push-T env on the `fast` preset: API conformance, determinism, errors, task quantities, the expert."""

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from twinbench.tasks import get_task
from twinbench.tasks.push_t import PushTConfig, PushTEnv
from twinbench.tasks.push_t_expert import PushTExpert
from twinbench.transforms import planar_pose


@pytest.fixture(scope="module")
def env():
    e = PushTEnv(preset="fast")
    yield e
    e.close()


def test_registered_and_conforms_to_gymnasium(env):
    spec = get_task("push-t")
    assert spec.env_id == "twinbench/PushT-v0" and spec.n_grid_states == 16
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=0, options={"init_state": 3})
    assert set(obs) == {"pixels", "agent_pos"} and set(obs["pixels"]) == {"front", "wrist"}
    assert obs["pixels"]["front"].shape == (240, 240, 3) and obs["pixels"]["front"].dtype == np.uint8
    assert obs["agent_pos"].dtype == np.float32 and obs["agent_pos"].shape == (2,)
    np.testing.assert_allclose(obs["agent_pos"], env.config.pusher_start, atol=1e-3)
    assert info == {"is_success": False, "status": "ok", "msd": pytest.approx(env.goal_msd())}
    assert env._max_episode_steps == 1800 and env.metadata["render_fps"] == 30
    assert isinstance(env.task_description, str) and env.task_description
    np.testing.assert_array_equal(env.render(), obs["pixels"]["front"])


def test_initial_states_place_the_block_on_the_grid(env):
    for i, (dx, dy, dth) in [(0, (-0.05, -0.05, -135)), (7, (-0.05, 0.05, 135)), (10, (0.05, -0.05, 45))]:
        env.reset(seed=0, options={"init_state": i})
        x, y, th = env.block_pose()
        assert (x, y) == pytest.approx((0.5 + dx, dy), abs=1e-5)
        assert np.rad2deg(th) == pytest.approx(dth, abs=1e-3)
    env.reset(seed=5, options={"sampled": True})
    x, y, _ = env.block_pose()
    assert abs(x - 0.5) <= 0.075 + 1e-6 and abs(y) <= 0.075 + 1e-6


def test_goal_pose_gives_zero_distance_full_coverage_and_yellow_overlay(env):
    env.reset(seed=0, options={"init_state": 0})
    env.scene.reset(env._q_start, {"tblock": env.goal})
    assert env.goal_msd() == pytest.approx(0.0, abs=1e-12)
    assert env.coverage() == pytest.approx(1.0)
    env.scene.reset(env._q_start, {"tblock": planar_pose(0.5, 0.2, 0.0)})  # 20 cm away: no overlap
    assert env.coverage() == 0.0 and env.goal_msd() == pytest.approx(0.04, rel=1e-6)
    front = env._observe()["pixels"]["front"].astype(float)
    mask = env._goal_overlay
    assert 0.005 < mask.mean() < 0.2  # the goal T is a small part of the view
    inside, outside = front[mask].mean(0), front[~mask].mean(0)
    assert inside[0] - inside[2] > outside[0] - outside[2] + 30  # yellow tint: red up, blue down


def test_pushing_moves_the_block_and_reward_is_coverage(env):
    env.reset(seed=0, options={"init_state": 0})
    before = env.block_pose()
    for _ in range(60):  # drive the pusher straight through the block's position
        obs, reward, term, trunc, info = env.step(np.array(before[:2], np.float32))
    after = env.block_pose()
    assert np.linalg.norm(after[:2] - before[:2]) > 0.01
    assert reward == pytest.approx(env.coverage()) and info["status"] == "ok"
    assert info["msd"] == pytest.approx(env.goal_msd())


def test_same_seed_and_state_give_identical_episodes(env):
    rng = np.random.default_rng(0)
    actions = rng.uniform([0.3, -0.1], [0.5, 0.1], size=(15, 2)).astype(np.float32)
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=3, options={"init_state": 5})
        for a in actions:
            obs, *_ = env.step(a)
        pixels = obs["pixels"]
        runs.append((pixels["front"].copy(), pixels["wrist"].copy(), env.scene.particles("tblock")))
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_bad_actions_raise_and_divergence_is_a_sim_error(env):
    env.reset(seed=0, options={"init_state": 0})
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(3))
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0.0]))
    with pytest.raises(ValueError, match="init_state"):
        env.reset(options={"init_state": -1})
    env.scene.state.v.assign(np.full((env.scene.model.num_particles, 3), 1e5, np.float32))
    obs, reward, term, trunc, info = env.step(np.array([0.3, 0.0], np.float32))
    assert info["status"] == "sim_error" and term and not info["is_success"]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.array([0.3, 0.0], np.float32))


def test_gymnasium_make_and_render_views_side_by_side():
    import gymnasium

    env = gymnasium.make("twinbench/PushT-v0", preset="fast", render_views="front+wrist")
    assert isinstance(env.unwrapped, PushTEnv)
    obs, _ = env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (240, 480, 3)
    np.testing.assert_array_equal(frame[:, 240:], obs["pixels"]["wrist"])
    with pytest.raises(ValueError, match="render_views"):
        PushTEnv(preset="fast", render_views="top")


def test_presets_are_named_and_validated():
    assert PushTConfig.preset("fast").particle_spacing == 0.015
    assert PushTConfig.preset("reference").substeps == 667
    with pytest.raises(ValueError, match="preset"):
        PushTConfig.preset("turbo")


def _run_expert(env, state: int) -> tuple[bool, int]:
    obs, _ = env.reset(seed=0, options={"init_state": state})
    expert = PushTExpert(env)
    steps = 0
    while True:
        obs, _, term, trunc, info = env.step(expert.select_action(obs))
        steps += 1
        if term or trunc:
            return info["is_success"], steps


@pytest.mark.parametrize("state", [0, 9])
def test_expert_solves_grid_states(env, state):
    success, steps = _run_expert(env, state)
    assert success, f"expert failed on grid state {state}"
    assert steps < env._max_episode_steps


@pytest.mark.slow
def test_expert_solves_at_least_12_of_16_grid_states(env):
    results = [_run_expert(env, i)[0] for i in range(16)]
    assert sum(results) >= 12, results
