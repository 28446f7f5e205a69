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


def test_features_declared_before_any_env_and_policy_made_from_them(tiny_act_checkpoint):
    """As LeRobot's own env configs: the config knows its features (from the task and the twin's
    description) before envs exist, so make_policy(cfg, env_cfg=...) works first; they equal the envs'."""
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies import make_policy
    from lerobot_env_twinbench import TwinbenchEnv

    cfg = TwinbenchEnv(task="PushT-v0", preset="fast")
    assert {k: v.shape for k, v in cfg.features.items()} == {
        "action": (2,), "pixels/front": (240, 240, 3), "pixels/wrist": (240, 240, 3), "agent_pos": (2,)}
    assert cfg.fps == 30
    policy_cfg = PreTrainedConfig.from_pretrained(tiny_act_checkpoint)
    policy_cfg.pretrained_path = tiny_act_checkpoint
    make_policy(policy_cfg, env_cfg=cfg)  # no env made
    grasp = TwinbenchEnv(task="ToyPacking-v0", preset="fast", env_kwargs='{"environment_state": true}')
    assert grasp.features["action"].shape == (8,) and grasp.features["agent_pos"].shape == (8,)
    assert grasp.features_map["environment_state"] == "observation.environment_state"
    declared = (dict(grasp.features), dict(grasp.features_map), grasp.fps)
    vec = grasp.create_envs(n_envs=1)["twinbench"][0]  # checks the envs' spaces against the declaration
    vec.close()
    assert (grasp.features, grasp.features_map, grasp.fps) == declared


def test_disable_env_checker_is_honoured():
    from gymnasium.wrappers.common import PassiveEnvChecker
    from lerobot_env_twinbench import TwinbenchEnv

    def checked(cfg):
        vec = cfg.create_envs(n_envs=1)["twinbench"][0]
        try:
            env, found = vec.envs[0], False
            while hasattr(env, "env"):
                found = found or isinstance(env, PassiveEnvChecker)
                env = env.env
            return found
        finally:
            vec.close()

    assert not checked(TwinbenchEnv(task="PointReach-v0"))  # LeRobot's default: disable_env_checker=True
    assert checked(TwinbenchEnv(task="PointReach-v0", disable_env_checker=False))


@pytest.fixture(scope="module")
def tiny_diffusion_checkpoint(tmp_path_factory):
    """A random, small Diffusion Policy for the push-T env's spaces, its ResNet backbone random too (no
    download), saved with its processors."""
    pytest.importorskip("diffusers", reason="Diffusion Policy needs diffusers (the lerobot extra)")
    import torch
    from lerobot.configs.types import FeatureType, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    out = tmp_path_factory.mktemp("diffusion") / "pretrained_model"
    cams = ("front", "wrist")
    inputs = {f"observation.images.{c}": PolicyFeature(FeatureType.VISUAL, (3, 240, 240)) for c in cams}
    inputs["observation.state"] = PolicyFeature(FeatureType.STATE, (2,))
    torch.manual_seed(0)
    action = {"action": PolicyFeature(FeatureType.ACTION, (2,))}
    cfg = DiffusionConfig(input_features=inputs, output_features=action,
                          n_obs_steps=2, horizon=8, n_action_steps=4, crop_shape=(96, 96),
                          pretrained_backbone_weights=None, use_group_norm=True, down_dims=(32, 64),
                          diffusion_step_embed_dim=32, spatial_softmax_num_keypoints=16,
                          num_train_timesteps=10, num_inference_steps=2, device="cpu")
    policy = DiffusionPolicy(cfg)
    stats = {"observation.state": {"min": torch.tensor([0.2, -0.3]), "max": torch.tensor([0.8, 0.3])},
             "action": {"min": torch.tensor([0.2, -0.3]), "max": torch.tensor([0.8, 0.3])}}
    for c in cams:
        stats[f"observation.images.{c}"] = {"mean": torch.full((3, 1, 1), 0.5),
                                            "std": torch.full((3, 1, 1), 0.25)}
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    for obj in (policy, pre, post):
        obj.save_pretrained(out)
    return out


@pytest.mark.slow  # about 2 minutes on 2 shared cores
def test_lerobot_eval_runs_a_random_diffusion_policy(tiny_diffusion_checkpoint, tmp_path):
    """`lerobot-eval --env.type=twinbench` with Diffusion Policy (the lerobot extra brings diffusers)."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    exe = shutil.which("lerobot-eval", path=str(Path(sys.executable).parent))
    assert exe, "lerobot-eval is not installed beside this python"
    out = subprocess.run([exe, f"--policy.path={tiny_diffusion_checkpoint}", "--policy.device=cpu",
                          "--env.type=twinbench", "--env.task=PushT-v0", "--env.preset=fast",
                          "--env.episode_seconds=0.3", "--eval.n_episodes=1", "--eval.batch_size=1",
                          f"--output_dir={tmp_path / 'eval'}"], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    info = json.loads((tmp_path / "eval" / "eval_info.json").read_text())
    assert info["overall"]["n_episodes"] == 1
    assert np.isfinite(info["per_task"][0]["metrics"]["sum_rewards"]).all()
