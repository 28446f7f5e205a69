"""The study's behaviour cloning: checkpoints per data size and epoch count, each with its training loss,
loadable as `cnn:` policy specs; a second call reuses them. (Recording needs a real workcell: the study's
end-to-end run covers it.)"""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("torch")

from twinbench.errors import InputError  # noqa: E402
from twinbench.policies import parse_policy_spec  # noqa: E402
from twinbench.policies.cnn import load_policy  # noqa: E402
from twinbench.study.bc import bc_size, train_checkpoints  # noqa: E402


def demos(n_episodes: int = 3, steps: int = 6, size: int = 16) -> dict:
    rng = np.random.default_rng(0)
    n = n_episodes * steps
    return {"images": rng.integers(0, 255, (n, size, size, 3), dtype=np.uint8),
            "agent_pos": rng.uniform(0.2, 0.6, (n, 2)).astype(np.float32),
            "actions": rng.uniform(0.2, 0.6, (n, 2)).astype(np.float32),
            "episode": np.repeat(np.arange(n_episodes), steps).astype(np.int32)}


def test_checkpoints_per_data_size_and_epochs(tmp_path):
    data = demos()
    logs = []
    paths = train_checkpoints(data, tmp_path, (1, 3, 9), (1, 2), image_size=16, log=logs.append)
    # data size 9 is capped at the 3 demonstrations there are (the same checkpoints as size 3)
    assert [p.name for p in paths] == ["bc-d1-e1", "bc-d1-e2", "bc-d3-e1", "bc-d3-e2"]
    for p in paths:
        rec = json.loads((p / "train.json").read_text())
        assert rec["frames"] == 6 * rec["demos"] and len(rec["loss_per_epoch"]) == rec["epochs"]
        assert rec["loss"] == rec["loss_per_epoch"][-1] > 0
        cfg, _ = load_policy(p)
        assert cfg.extra["demos"] == rec["demos"] and cfg.relative
        spec = parse_policy_spec(f"{p.name}=cnn:{p}")
        assert (spec.kind, spec.name, spec.checkpoint) == ("cnn", p.name, p.name)
    # the 1-epoch checkpoint is the 2-epoch run after its first epoch
    one, two = (json.loads((tmp_path / f"bc-d3-e{e}" / "train.json").read_text()) for e in (1, 2))
    assert two["loss_per_epoch"][0] == one["loss"]
    # again: nothing is retrained
    logs.clear()
    assert train_checkpoints(data, tmp_path, (1, 3, 9), (1, 2), image_size=16, log=logs.append) == paths
    assert logs == []


def test_unknown_size():
    with pytest.raises(InputError, match="small"):
        bc_size("huge")


TINY = {"act": {"chunk_size": 4, "n_action_steps": 2, "dim_model": 32, "n_heads": 2, "dim_feedforward": 64,
                "n_encoder_layers": 1, "n_decoder_layers": 1, "latent_dim": 8, "n_vae_encoder_layers": 1},
        "dp": {"horizon": 8, "n_action_steps": 4, "down_dims": (16, 32), "crop_shape": (14, 14),
               "diffusion_step_embed_dim": 16, "spatial_softmax_num_keypoints": 8, "n_groups": 4}}


@pytest.mark.parametrize("arch", ["act", "dp"])
def test_lerobot_checkpoints_train_reproducibly_and_load_through_the_lerobot_adapter(tmp_path, arch):
    """LeRobot ACT and Diffusion Policy trained on demonstrations whose action is a known function of the
    state: the loss falls, the same seed gives the same weights, and the checkpoint loads from its policy
    spec like any LeRobot checkpoint, taking the env's 240x240 front image down to its training size, and
    acts (Diffusion Policy: from its two-step observation queue)."""
    pytest.importorskip("lerobot", reason="needs the lerobot extra (make install EXTRAS='dev lerobot')")
    from twinbench.policies import make_policy
    from twinbench.study.bc import lerobot_spec, train_lerobot_checkpoints

    data = demos(n_episodes=4, steps=8)
    data["actions"] = data["agent_pos"] + np.float32(0.05)  # learnable from the state alone
    kw = {"arch": arch, "settings": TINY[arch], "batch_size": 8, "lr": 1e-3, "log": lambda m: None}
    epochs = (1, 5) if arch == "act" else (1, 15)  # noise prediction learns more slowly
    paths = train_lerobot_checkpoints(data, tmp_path / "a", (2, 4), epochs, **kw)
    assert [p.name for p in paths] == [f"{arch}-d{d}-e{e}" for d in (2, 4) for e in epochs]
    rec = json.loads((paths[-1] / "train.json").read_text())
    assert rec["frames"] == 32 and len(rec["loss_per_epoch"]) == epochs[-1]
    assert rec["arch"] == f"lerobot-{arch}"
    # ACT's L1 halves; Diffusion Policy's noise prediction error starts at the noise's variance (1)
    assert rec["loss_per_epoch"][-1] < (0.5 if arch == "act" else 0.7) * rec["loss_per_epoch"][0]
    assert not list((tmp_path / "a").glob("*.partial"))
    again = train_lerobot_checkpoints(data, tmp_path / "b", (2,), (epochs[-1],), **kw)[0]
    weights = [(p / "model.safetensors").read_bytes() for p in (paths[1], again)]
    assert weights[0] == weights[1]

    class Env:  # what make_policy reads of an env: its spaces and task text
        task_description = ""
        unwrapped = property(lambda self: self)

        class action_space:  # noqa: N801
            low, high, shape = np.zeros(2, np.float32), np.ones(2, np.float32), (2,)

    spec = parse_policy_spec(lerobot_spec(paths[-1]))
    assert (spec.kind, spec.name) == ("lerobot", paths[-1].name)
    policy = make_policy(spec, "push-t", Env(), seed=0)
    rng = np.random.default_rng(1)
    policy.reset()
    for _ in range(3):
        obs = {"pixels": {"front": rng.integers(0, 255, (240, 240, 3), dtype=np.uint8)},
               "agent_pos": np.array([0.4, 0.3], np.float32)}
        action = np.asarray(policy.select_action(obs))
        assert action.shape == (2,) and np.all(np.isfinite(action))


def test_unknown_lerobot_architecture(tmp_path):
    from twinbench.study.bc import train_lerobot_checkpoints

    with pytest.raises(InputError, match="'act', 'dp'"):
        train_lerobot_checkpoints(demos(), tmp_path, (1,), (1,), arch="pi0")
