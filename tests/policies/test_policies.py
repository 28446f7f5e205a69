"""Policy specs, the chunk queue and degraded experts (known mapping, determinism, monotone quality)."""

import numpy as np
import pytest

from twinbench.evaluation.rollout import run_episode
from twinbench.policies import ChunkedPolicy, DegradedPolicy, PolicyError, make_policy, parse_policy_spec
from twinbench.policies.degraded import level_to_train_step
from twinbench.tasks import get_task


def test_spec_strings():
    s = parse_policy_spec("expert")
    assert (s.kind, s.name, s.checkpoint, s.train_step, s.level) == ("expert", "expert", "", None, None)
    s = parse_policy_spec("expert@0.3")
    assert (s.name, s.checkpoint, s.train_step, s.level) == ("expert", "step_70000", 70000, 0.3)
    s = parse_policy_spec("remote:ws://127.0.0.1:8000")
    assert (s.kind, s.target, s.checkpoint) == ("remote", "ws://127.0.0.1:8000", "127.0.0.1")
    s = parse_policy_spec("act=lerobot:out/train/act/checkpoints/020000/pretrained_model")
    assert (s.kind, s.name, s.checkpoint, s.train_step) == ("lerobot", "act", "step_20000", 20000)
    s = parse_policy_spec("lerobot:models/my_act")
    assert (s.checkpoint, s.train_step) == ("my_act", None)
    for bad in ["", "expert@x", "expert@1.5", "remote:http://x", "foo", "bad name=expert", "lerobot:"]:
        with pytest.raises(ValueError):
            parse_policy_spec(bad)
    assert [level_to_train_step(v) for v in (0.0, 0.25, 1.0)] == [100000, 75000, 0]


class Counter(ChunkedPolicy):
    """Chunks [k, k+1, ..., k+4] (as 1-D actions) with k the number of predictions so far."""

    def predict_chunk(self, obs):
        k = 10 * self.n_predictions
        return np.arange(k, k + 5, dtype=float)[:, None]


def test_chunk_queue_executes_n_action_steps():
    p = Counter(n_action_steps=3)
    got = [float(p.select_action({})[0]) for _ in range(7)]
    assert got == [0, 1, 2, 10, 11, 12, 20] and p.n_predictions == 3 and p.chunk_size == 5
    p.reset()  # drops the queued rest of the chunk
    assert float(p.select_action({})[0]) == 30
    q = Counter()  # whole chunk
    assert [float(q.select_action({})[0]) for _ in range(6)] == [0, 1, 2, 3, 4, 10]

    class Empty(ChunkedPolicy):
        def predict_chunk(self, obs):
            return np.zeros((0, 2))

    with pytest.raises(PolicyError, match="shape"):
        Empty().select_action({})


class Zero:
    def reset(self):
        pass

    def select_action(self, obs):
        return np.zeros(2, np.float32)


def test_degraded_noise_scale_and_determinism():
    low, high = -np.ones(2), np.ones(2)
    assert np.all(DegradedPolicy(Zero(), 0.0, 1, low, high).select_action({}) == 0)
    a = DegradedPolicy(Zero(), 0.2, 7, low, high)
    first = np.array([a.select_action({}) for _ in range(2000)])
    a.reseed(7)
    again = np.array([a.select_action({}) for _ in range(2000)])
    assert np.array_equal(first, again)
    # glitches (prob 0.2 * 0.5 = 0.1) are stale or uniform; the rest is N(0, (0.2 * 1.0 * 1)^2)
    std = np.std(first[np.abs(first).max(axis=1) < 0.6])
    assert 0.17 < std < 0.21
    with pytest.raises(ValueError):
        DegradedPolicy(Zero(), 1.2, 0, low, high)
    with pytest.raises(ValueError, match="finite"):
        DegradedPolicy(Zero(), 0.5, 0, -np.inf * low, high)


def test_degraded_expert_quality_decreases_with_level():
    task = get_task("point-reach")
    env = task.make_env()
    rates = []
    for level in (0.0, 0.5, 1.0):
        pol = make_policy(f"expert@{level}", task, env)
        rates.append(np.mean([run_episode(env, pol, init_state=8 + k, seed=k).success for k in range(40)]))
    assert rates[0] == 1.0 and rates[0] > rates[1] > rates[2] and rates[2] < 0.5


def test_missing_extras_name_the_install_command(tmp_path):
    import importlib.util

    from twinbench.evaluation.runner import evaluate
    from twinbench.evaluation.store import ResultsStore

    if importlib.util.find_spec("lerobot") is None:
        with pytest.raises(ImportError, match=r"twinbench\[lerobot\]"):
            from twinbench.policies.lerobot_adapter import LeRobotPolicy

            LeRobotPolicy(tmp_path)
        # inside a run, a policy that cannot be built is a policy_error naming the extra
        store = ResultsStore(tmp_path / "r.sqlite")
        recs = evaluate("point-reach", [f"lerobot:{tmp_path}"], 1, 0, "lr", store, output_dir=tmp_path)
        assert recs[0].status == "policy_error" and "twinbench[lerobot]" in recs[0].metrics["error"]
    if importlib.util.find_spec("ray") is None:
        with pytest.raises(ImportError, match=r"twinbench\[ray\]"):
            evaluate("point-reach", ["expert"], 1, 1, "ray", ResultsStore(tmp_path / "r2.sqlite"),
                     backend="ray", output_dir=tmp_path)
