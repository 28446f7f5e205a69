"""TwinVectorEnv: many worlds of one twin in one physics launch, each world bit-identical to a TwinEnv run
alone, gymnasium's NEXT_STEP autoreset, per-world reset and per-world divergence."""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest

import twinbench  # noqa: F401  (registers the env ids)
from twinbench.env import TwinEnv, TwinVectorEnv

KW = {"preset": "fast", "episode_seconds": 0.2, "settle_steps": 2}  # 6-step episodes: autoreset within a test
DIRS = np.array([[1, 0], [0, 1], [-1, 0], [0.7, -0.7]], np.float32)


def _actions(start: np.ndarray, k: int) -> np.ndarray:
    """World i's pusher target at step k: its start moved 8 mm per step along DIRS[i]."""
    return (start + 0.008 * (k + 1) * DIRS[: len(start)]).astype(np.float32)


def _same(a, b, where: str) -> None:
    if isinstance(a, dict):
        assert a.keys() == b.keys(), where
        for key in a:
            _same(a[key], b[key], f"{where}.{key}")
    else:
        assert np.array_equal(np.asarray(a), np.asarray(b)), where


def test_make_vec_gives_the_vector_env_with_batched_spaces():
    envs = gymnasium.make_vec("twinbench/PushT-v0", num_envs=3, vectorization_mode="vector_entry_point",
                              **KW)
    assert isinstance(envs, TwinVectorEnv) and envs.num_envs == 3
    assert envs.metadata["autoreset_mode"] == gymnasium.vector.AutoresetMode.NEXT_STEP
    assert envs.action_space.shape == (3, 2)
    obs, infos = envs.reset(seed=3)
    assert envs.observation_space.contains(obs)
    assert obs["pixels"]["front"].shape == (3, 240, 240, 3)
    assert infos["_is_success"].all() and not infos["is_success"].any()
    # reset(seed=s) seeds world i with s + i: grid states s + i, as TwinEnv.reset(seed=s + i) picks
    single = TwinEnv("push-t", **KW)
    for i in range(3):
        o, _ = single.reset(seed=3 + i)
        _same(o, {k: (v[i] if not isinstance(v, dict) else {c: a[i] for c, a in v.items()})
                  for k, v in obs.items()}, f"world {i}")
    with pytest.raises(ValueError, match="reset_mask"):
        envs.reset(options={"reset_mask": [True, False]})
    with pytest.raises(ValueError, match="init_state"):
        envs.reset(options={"init_state": [0, 1]})
    with pytest.raises(ValueError, match="actions"):
        envs.step(np.zeros((2, 2), np.float32))


def test_four_worlds_reproduce_four_single_runs_bit_for_bit_across_autoreset():
    """The batched env against gymnasium's SyncVectorEnv of four separate TwinEnvs (the reference for
    autoreset semantics): identical observations, rewards, flags and infos over two episodes."""
    n = 4
    states = [0, 5, 10, 15]
    vec = TwinVectorEnv("push-t", n, **KW)
    ref = gymnasium.vector.SyncVectorEnv([lambda: TwinEnv("push-t", **KW) for _ in range(n)])
    opts = {"init_state": states}
    got_obs, got_info = vec.reset(seed=1, options=opts)
    ref.reset(seed=1)  # SyncVectorEnv takes one options dict for all: each env is then reset by hand
    for i, env in enumerate(ref.envs):
        env.reset(seed=1 + i, options={"init_state": states[i]})
    start = got_obs["agent_pos"].copy()
    moved = False
    for k in range(9):  # an episode is 6 steps: step 7 autoresets every world, then 2 more steps
        a = _actions(start, k)
        got = vec.step(a)
        want = ref.step(a)
        for name, g, w in zip(("obs", "reward", "terminated", "truncated", "info"), got, want, strict=True):
            _same(g, w, f"step {k} {name}")
        moved |= bool(np.any(got[4].get("msd", 0) != got_info["msd"]))
    assert got[2].sum() + got[3].sum() == 0 and vec._autoreset.sum() == 0  # mid second episode
    assert moved
    for i, env in enumerate(ref.envs):
        np.testing.assert_array_equal(vec.twin.particles(vec.envs[i].state, "tblock"),
                                      env.unwrapped.twin.particles(env.unwrapped.state, "tblock"))


def test_a_diverging_world_ends_alone_and_comes_back_after_reset():
    vec = TwinVectorEnv("push-t", 3, **KW)
    alone = TwinEnv("push-t", **KW)
    obs, _ = vec.reset(seed=0, options={"init_state": [2, 2, 2]})
    alone.reset(seed=0, options={"init_state": 2})
    state = vec.envs[1].state
    v = state.physics.v.numpy()
    span = vec.twin._span(state)
    v[span][5] = np.nan  # world 1's block blows up
    state.physics.v.assign(v)
    a = obs["agent_pos"]
    obs, r, term, trunc, info = vec.step(a)
    o1, r1, *_ = alone.step(a[0])
    assert list(info["status"]) == ["ok", "sim_error", "ok"]
    assert list(term) == [False, True, False]
    for i in (0, 2):
        np.testing.assert_array_equal(obs["pixels"]["front"][i], o1["pixels"]["front"])
        assert r[i] == r1
    assert "diverged" in info["error"][1]
    obs, r, term, trunc, info = vec.step(a)  # world 1 autoresets, the others step on
    assert list(info["status"]) == ["ok", "ok", "ok"] and not term.any()
    o2, *_ = alone.step(a[0])
    np.testing.assert_array_equal(obs["pixels"]["front"][0], o2["pixels"]["front"])
    assert np.isfinite(vec.twin.particles(state, "tblock")).all()


def test_partial_reset_leaves_the_other_worlds_alone():
    vec = TwinVectorEnv("push-t", 2, **KW)
    obs, _ = vec.reset(seed=0, options={"init_state": [1, 4]})
    obs, *_ = vec.step(_actions(obs["agent_pos"], 0))
    before = vec.twin.particles(vec.envs[0].state, "tblock")
    obs2, infos = vec.reset(options={"reset_mask": [False, True], "init_state": [0, 7]})
    np.testing.assert_array_equal(vec.twin.particles(vec.envs[0].state, "tblock"), before)
    np.testing.assert_array_equal(obs2["pixels"]["front"][0], obs["pixels"]["front"][0])
    assert list(infos["_is_success"]) == [False, True]
    single = TwinEnv("push-t", **KW)
    o, _ = single.reset(options={"init_state": 7})
    np.testing.assert_array_equal(obs2["pixels"]["front"][1], o["pixels"]["front"])


def test_gripper_worlds_with_colliders_match_single_runs():
    """Rope routing (clip collider, gripper latch): two worlds against two single envs."""
    kw = {"preset": "fast", "episode_seconds": 1.0, "settle_steps": 2}
    vec = TwinVectorEnv("rope-routing", 2, **kw)
    obs, _ = vec.reset(options={"init_state": [3, 20]})
    singles = [TwinEnv("rope-routing", **kw) for _ in range(2)]
    for env, s in zip(singles, (3, 20), strict=True):
        env.reset(options={"init_state": s})
    a = obs["agent_pos"].copy()
    for k in range(8):
        a[:, 2] -= 0.01  # down towards the rope, then close the gripper
        a[:, 7] = 1.0 if k >= 5 else 0.0
        obs, r, *_ , info = vec.step(a)
        for i, env in enumerate(singles):
            o, ri, *_, inf = env.step(a[i])
            np.testing.assert_array_equal(obs["pixels"]["front"][i], o["pixels"]["front"])
            np.testing.assert_array_equal(obs["agent_pos"][i], o["agent_pos"])
            assert info["grasp"][i] == inf["grasp"]
    for i, env in enumerate(singles):
        np.testing.assert_array_equal(vec.twin.particles(vec.envs[i].state, "rope"),
                                      env.twin.particles(env.state, "rope"))


def test_cameras_keyword_observes_only_the_named_cameras_with_the_same_pixels():
    """`cameras="front"`: only the front camera is rendered and observed, its pixels (goal overlay and
    camera response included) equal to those of an env observing every camera; bad names are refused."""
    import dataclasses

    from twinbench.gaussians.response import CameraResponse
    from twinbench.tasks import get_task

    cell = get_task("push-t").task_cls(None).default_twin("fast")
    noisy = CameraResponse(gamma=1.2, noise_std=3.0, blur_sigma=0.5)
    cell = dataclasses.replace(cell, cameras=tuple(dataclasses.replace(c, response=noisy)
                                                   for c in cell.cameras))
    kw = {k: v for k, v in KW.items() if k != "preset"}
    both = TwinEnv("push-t", twin=cell, **kw)
    front = TwinEnv("push-t", twin=cell, cameras="front", **kw)
    assert set(both.observation_space["pixels"].spaces) == {"front", "wrist"}
    assert set(front.observation_space["pixels"].spaces) == {"front"}
    o_both, _ = both.reset(seed=1, options={"init_state": 3})
    o_front, _ = front.reset(seed=1, options={"init_state": 3})
    blind = TwinEnv("push-t", twin=cell, cameras="", **kw)  # no camera: the same physics, no images
    o_blind, _ = blind.reset(seed=1, options={"init_state": 3})
    assert o_blind["pixels"] == {} and blind.observation_space.contains(o_blind)
    with pytest.raises(RuntimeError, match="no camera"):
        blind.render()
    for _ in range(2):
        a = o_both["agent_pos"] + np.float32(0.01)
        o_both, *_ = both.step(a)
        o_front, *_ = front.step(a)
        o_blind, *_ = blind.step(a)
    assert front.observation_space.contains(o_front) and list(o_front["pixels"]) == ["front"]
    assert np.array_equal(o_front["pixels"]["front"], o_both["pixels"]["front"])
    assert np.array_equal(o_front["agent_pos"], o_both["agent_pos"])
    assert np.array_equal(o_blind["agent_pos"], o_both["agent_pos"]) and o_blind["pixels"] == {}
    for bad in ("top", "front+front", "+"):
        with pytest.raises(ValueError, match="cameras"):
            TwinEnv("push-t", cameras=bad, **KW)
    with pytest.raises(ValueError, match="render_views"):
        TwinEnv("push-t", cameras="front", render_views="wrist", **KW)
    blind_vec = TwinVectorEnv("push-t", num_envs=2, cameras="", **KW)
    obs, _ = blind_vec.reset(seed=0)
    obs, *_ = blind_vec.step(np.stack([obs["agent_pos"][0], obs["agent_pos"][1]]))
    assert obs["pixels"] == {} and obs["agent_pos"].shape == (2, 2)
    vec = TwinVectorEnv("push-t", num_envs=2, cameras="wrist", **KW)
    obs, _ = vec.reset(seed=0)
    assert list(obs["pixels"]) == ["wrist"] and obs["pixels"]["wrist"].shape[0] == 2
    obs, *_ = vec.step(np.stack([obs["agent_pos"][0], obs["agent_pos"][1]]))
    assert vec.observation_space.contains(obs)
