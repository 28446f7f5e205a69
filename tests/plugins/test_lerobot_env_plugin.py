"""The LeRobot env plugin: LeRobot's own eval loop (eval_policy_all, async vector envs, videos) drives a
twinbench env. Runs only with the lerobot extra (Python >= 3.12)."""

import json

import numpy as np
import pytest

pytest.importorskip("lerobot", reason="needs the lerobot extra (make install EXTRAS='dev lerobot')")


def test_features_and_task_resolution():
    from lerobot_env_twinbench import TwinbenchEnv, resolve_env_id

    assert resolve_env_id("PushT-v0") == resolve_env_id("push-t") == "twinbench/PushT-v0"
    assert resolve_env_id("twinbench/PointReach-v0") == "twinbench/PointReach-v0"
    with pytest.raises(ValueError, match="PushT-v0"):
        resolve_env_id("Nope-v0")
    with pytest.raises(ValueError, match="JSON"):
        TwinbenchEnv(task="PushT-v0", env_kwargs="{bad")
    cfg = TwinbenchEnv(task="PointReach-v0")
    envs = cfg.create_envs(n_envs=2)
    vec = envs["twinbench"][0]
    try:
        assert cfg.features["pixels/front"].shape == (64, 64, 3) and cfg.features["action"].shape == (2,)
        assert cfg.features_map["pixels/wrist"] == "observation.images.wrist"
        assert cfg.features_map["agent_pos"] == "observation.state" and cfg.fps == 10
        # LeRobot's reset passes its own option; episode k starts from grid state (seed + k) mod 8
        obs, _ = vec.reset(seed=[3, 12], options={"lerobot_new_rollout": True})
        from twinbench.tasks.point_reach import grid_state

        assert np.allclose(obs["agent_pos"], [grid_state(3), grid_state(4)], atol=1e-6)
        assert list(vec.call("task")) == list(vec.call("task_description"))
        assert vec.call("task")[0].startswith("move the point")
    finally:
        vec.close()


def test_lerobot_eval_policy_drives_twinbench_async(tiny_act_checkpoint, tmp_path):
    """Random small ACT, 2 async (forkserver) vector envs, a 6-step push-T episode each: LeRobot's
    eval_policy_all writes per-episode results and one mp4 per episode at the env's integer fps."""
    import imageio.v3 as iio
    import torch
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.envs import close_envs, make_env, make_env_pre_post_processors
    from lerobot.policies import make_policy, make_pre_post_processors
    from lerobot.scripts.lerobot_eval import eval_policy_all
    from lerobot_env_twinbench import TwinbenchEnv

    env_cfg = TwinbenchEnv(task="PushT-v0", preset="fast", episode_seconds=0.2)
    envs = make_env(env_cfg, n_envs=2, use_async_envs=True)
    vec = envs["twinbench"][0]
    assert type(vec).__name__ == "AsyncVectorEnv"
    policy_cfg = PreTrainedConfig.from_pretrained(tiny_act_checkpoint)
    policy_cfg.pretrained_path = tiny_act_checkpoint
    policy = make_policy(policy_cfg, env_cfg=env_cfg)
    pre, post = make_pre_post_processors(policy_cfg, pretrained_path=str(tiny_act_checkpoint))
    env_pre, env_post = make_env_pre_post_processors(env_cfg, policy_cfg)
    try:
        with torch.no_grad():
            info = eval_policy_all(envs, policy, env_pre, env_post, pre, post, n_episodes=2,
                                   max_episodes_rendered=2, videos_dir=tmp_path / "videos", start_seed=1000)
    finally:
        close_envs(envs)
    overall = info["overall"]
    assert overall["n_episodes"] == 2 and overall["pc_success"] == 0.0
    metrics = info["per_task"][0]["metrics"]
    assert len(metrics["sum_rewards"]) == 2 and all(np.isfinite(metrics["sum_rewards"]))
    assert len(overall["video_paths"]) == 2
    for path in overall["video_paths"]:
        frames = iio.imread(path)
        assert frames.shape == (6, 240, 240, 3)  # reset frame + 6 steps, cut at the done step
        assert frames.std() > 1.0  # a rendered scene, not a blank
    json.dumps(info)  # what lerobot-eval writes as eval_info.json
