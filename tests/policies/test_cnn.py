"""The small CNN policy (`cnn:DIR`): seeded training is reproducible, a checkpoint loads through the policy
spec and acts in chunks, and training learns a known image -> action mapping."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from gymnasium.spaces import Box  # noqa: E402

from twinbench.errors import InputError  # noqa: E402
from twinbench.policies import make_policy, parse_policy_spec  # noqa: E402
from twinbench.policies.cnn import (  # noqa: E402
    CNNPolicy,
    chunk_targets,
    episode_window,
    load_policy,
    make_config,
    save_policy,
    train,
)

SMALL = {"image_size": 16, "channels": (8, 16), "hidden": 32, "chunk": 3, "n_action_steps": 2}


def dot_data(n: int, seed: int, size: int = 16):
    """Images with one bright 3x3 square; the action is its centre (pixels scaled to [0, 1]) minus agent_pos:
    relative targets that only the image determines."""
    rng = np.random.default_rng(seed)
    images = np.full((n, size, size, 3), 20, np.uint8)
    centres = rng.integers(1, size - 1, (n, 2))
    for k, (i, j) in enumerate(centres):
        images[k, i - 1:i + 2, j - 1:j + 2] = 230
    agent_pos = rng.uniform(0, 1, (n, 2)).astype(np.float32)
    actions = (centres / (size - 1)).astype(np.float32)
    return images, agent_pos, actions, np.arange(n)  # one-step episodes: every chunk repeats the action


def test_chunk_targets_stop_at_the_episode_end():
    a = np.arange(5, dtype=np.float32)[:, None]
    t = chunk_targets(a, np.array([0, 0, 0, 1, 1]), 3)
    assert t[:, :, 0].tolist() == [[0, 1, 2], [1, 2, 2], [2, 2, 2], [3, 4, 4], [4, 4, 4]]


def test_episode_window_clamps_to_each_episode_and_marks_the_padding():
    idx, pad = episode_window(np.array([0, 0, 0, 1, 1]), [-1, 0, 1])
    assert idx.tolist() == [[0, 0, 1], [0, 1, 2], [1, 2, 2], [3, 3, 4], [3, 4, 4]]
    assert pad.tolist() == [[True, False, False], [False, False, False], [False, False, True],
                            [True, False, False], [False, False, True]]


def test_training_is_reproducible_with_a_seed():
    images, pos, act, ep = dot_data(48, 0)
    cfg = make_config(pos, act, ep, **SMALL)
    runs = [train(cfg, images, pos, act, ep, epochs=2, seed=s, batch_size=16) for s in (3, 3, 4)]
    (a, la), (b, lb), (c, lc) = runs
    assert la == lb and la != lc
    for k, v in a.state_dict().items():
        assert torch.equal(v, b.state_dict()[k]), k
    assert not all(torch.equal(v, c.state_dict()[k]) for k, v in a.state_dict().items())


def test_checkpoint_loads_through_the_policy_spec(tmp_path):
    images, pos, act, ep = dot_data(16, 1)
    cfg = make_config(pos, act, ep, **SMALL)
    net, _ = train(cfg, images, pos, act, ep, epochs=1, seed=0)
    save_policy(tmp_path / "ckpt-a", cfg, net)
    spec = parse_policy_spec(f"mine=cnn:{tmp_path / 'ckpt-a'}?n_action_steps=1")
    assert (spec.kind, spec.name, spec.checkpoint, spec.n_action_steps) == ("cnn", "mine", "ckpt-a", 1)
    env = SimpleNamespace(action_space=Box(0.2, 0.6, (2,), np.float32))
    policy = make_policy(f"mine=cnn:{tmp_path / 'ckpt-a'}", None, env)
    assert isinstance(policy, CNNPolicy)
    obs = {"pixels": {"front": np.zeros((40, 40, 3), np.uint8)},
           "agent_pos": np.array([0.4, 0.4], np.float32)}
    actions = [policy.select_action(obs) for _ in range(5)]
    assert all(a.shape == (2,) and a.dtype == np.float32 and np.all((a >= 0.2) & (a <= 0.6)) for a in actions)
    assert policy.chunk_size == 3 and policy.n_predictions == 3  # 2 of each chunk of 3 executed
    # the same weights as saved: the reloaded net predicts what the trained one does
    _, again = load_policy(tmp_path / "ckpt-a")
    for k, v in net.state_dict().items():
        assert torch.equal(v, again.state_dict()[k])


def test_bad_checkpoints_are_named(tmp_path):
    with pytest.raises(InputError, match="config.json and weights.pt"):
        load_policy(tmp_path)
    (tmp_path / "config.json").write_text('{"format": "other"}')
    (tmp_path / "weights.pt").write_bytes(b"x")
    with pytest.raises(InputError, match="not a cnn policy config"):
        load_policy(tmp_path)
    with pytest.raises(InputError, match="cnn:DIR"):
        parse_policy_spec("cnn")


def test_training_learns_a_known_image_to_action_mapping():
    images, pos, act, ep = dot_data(400, 2)
    test_images, test_pos, test_act, _ = dot_data(100, 3)
    cfg = make_config(pos, act, ep, **SMALL)
    trained, losses = train(cfg, images, pos, act, ep, epochs=25, seed=0, shift_px=0)
    untrained, _ = train(cfg, images, pos, act, ep, epochs=0, seed=0)
    space = Box(-2.0, 2.0, (2,), np.float32)

    def error(net):
        policy = CNNPolicy(cfg, net.eval(), space.low, space.high)
        pred = np.stack([policy.predict_chunk({"pixels": {"front": im}, "agent_pos": p})[0]
                         for im, p in zip(test_images, test_pos, strict=True)])
        return float(np.sqrt(np.mean((pred - test_act) ** 2)))

    assert losses[-1] < 0.2 * losses[0]
    # held-out images: the dot's position to within 1.5 pixels (of 15), the untrained net's error is ~5x
    assert error(trained) < 0.1 < error(untrained)
