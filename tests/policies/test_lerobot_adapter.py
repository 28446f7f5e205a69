"""The LeRobot observation mapping (numpy part; running a real LeRobot policy needs the lerobot extra)."""

import numpy as np
import pytest

from twinbench.policies.lerobot_adapter import lerobot_arrays
from twinbench.tasks import get_task


def test_observation_mapping_known_values():
    front = np.zeros((2, 3, 3), np.uint8)
    front[0, 1] = (255, 51, 0)  # row 0, column 1
    obs = {"pixels": {"front": front, "wrist": np.full((2, 3, 3), 102, np.uint8)},
           "agent_pos": np.array([0.1, -0.2], np.float32)}
    b = lerobot_arrays(obs, "push the T")
    f = b["observation.images.front"]
    assert f.shape == (1, 3, 2, 3) and f.dtype == np.float32
    assert f[0, :, 0, 1].tolist() == pytest.approx([1.0, 0.2, 0.0]) and f[0, :, 1, 1].tolist() == [0, 0, 0]
    assert np.allclose(b["observation.images.wrist"], 0.4)
    assert b["observation.state"].shape == (1, 2) and b["observation.state"][0, 1] == np.float32(-0.2)
    assert b["task"] == ["push the T"]
    env = get_task("point-reach").make_env()
    b = lerobot_arrays(env.reset(seed=0)[0], "")
    assert set(b) == {"observation.images.front", "observation.images.wrist", "observation.state", "task"}
    with pytest.raises(ValueError, match="uint8"):
        lerobot_arrays({"pixels": {"front": np.zeros((2, 2, 3))}, "agent_pos": np.zeros(2)}, "")


def test_lerobot_checkpoint_runs_as_lerobot_would(tiny_act_checkpoint, fast_env, tmp_path):
    """`lerobot:PATH` gives the action LeRobot's own eval pipeline gives for the same observation, runs
    an episode, and executes `n_action_steps` of a chunk when asked (twinbench's queue)."""
    import shutil

    import torch
    from lerobot.envs.utils import preprocess_observation

    from twinbench.evaluation.rollout import run_episode
    from twinbench.policies import make_policy

    task = get_task("push-t")
    pol = make_policy(f"lerobot:{tiny_act_checkpoint}", task, fast_env)
    obs, _ = fast_env.reset(seed=0, options={"init_state": 2})
    pol.reset()
    ours = pol.select_action(obs)
    batched = {"pixels": {c: img[None] for c, img in obs["pixels"].items()},
               "agent_pos": obs["agent_pos"][None]}
    ref_in = preprocess_observation(batched)
    ref_in["task"] = [fast_env.unwrapped.task]
    pol.policy.reset()
    with torch.inference_mode():
        ref = pol.postprocessor(pol.policy.select_action(pol.preprocessor(ref_in))).numpy()[0]
    assert ours.shape == (2,) and np.allclose(ours, ref, atol=1e-5)
    out = run_episode(fast_env, pol, init_state=2, seed=0, max_steps=3)
    assert (out.status, out.steps) == ("ok", 3)
    own = make_policy(f"lerobot:{tiny_act_checkpoint}?n_action_steps=1", task, fast_env)
    own.reset()
    assert own.own_queue and np.allclose(own.select_action(obs), ours, atol=1e-5)
    assert own.n_predictions == 1 and own.chunk_size == 4
    bare = tmp_path / "weights_only"
    bare.mkdir()
    for f in ("config.json", "model.safetensors"):
        shutil.copy(tiny_act_checkpoint / f, bare / f)
    with pytest.raises(ValueError, match=r"policy_preprocessor.json.*save_pretrained"):
        make_policy(f"lerobot:{bare}", task, fast_env)
