"""Websocket + msgpack remote policies: array round trip, served expert, chunks, errors, dead server."""

import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

from twinbench.evaluation.rollout import run_episode
from twinbench.policies import ChunkedPolicy, PolicyError
from twinbench.policies.protocol import packb, unpackb
from twinbench.policies.remote import RemotePolicy
from twinbench.policies.server import PolicyServer
from twinbench.tasks import get_task
from twinbench.tasks.point_reach import PointReachExpert


def test_msgpack_numpy_round_trip():
    rng = np.random.default_rng(0)
    arrays = {
        "u8": rng.integers(0, 255, (4, 5, 3), dtype=np.uint8),
        "f16": rng.normal(size=3).astype(np.float16),
        "f32": rng.normal(size=(2, 2)).astype(np.float32),
        "f64": np.array([np.pi, -0.0, np.inf]),
        "i64": np.array([-(2**62), 3], dtype=np.int64),
        "bool": np.array([True, False]),
        "big_endian": np.arange(3, dtype=">i4"),
        "scalar0d": np.array(2.5, dtype=np.float32),
        "empty": np.zeros((0, 7), dtype=np.float32),
        "strided": np.arange(20, dtype=np.int16).reshape(4, 5)[:, ::2],
    }
    msg = {"arrays": arrays, "np_scalar": np.float32(1.25), "text": "push",
           "nested": [1, {"x": arrays["u8"]}]}
    back = unpackb(packb(msg))
    for k, a in arrays.items():
        b = back["arrays"][k]
        assert b.dtype == a.dtype and b.shape == a.shape and np.array_equal(a, b), k
        assert b.flags.writeable
    assert back["np_scalar"] == np.float32(1.25) and type(back["np_scalar"]) is np.float32
    assert back["text"] == "push" and np.array_equal(back["nested"][1]["x"], arrays["u8"])
    with pytest.raises(ValueError, match="complex"):
        packb({"c": np.zeros(2, np.complex64)})


def test_served_expert_reaches_the_goal():
    env = get_task("point-reach").make_env()
    with PolicyServer(PointReachExpert, metadata={"policy": "expert"}) as server:
        pol = RemotePolicy(server.url, timeout_s=5, retries=1, prompt="reach")
        out = run_episode(env, pol, init_state=3, seed=0)
        assert (out.status, out.success, out.steps) == ("ok", True, 12)
        assert pol.metadata == {"policy": "expert"} and server.n_requests == 12
        assert pol.n_connects == 1  # one connection carries the whole episode
        pol.close()


class GoalChunks(ChunkedPolicy):
    """Four identical goal targets per chunk."""

    def predict_chunk(self, obs):
        assert obs["pixels"]["front"].dtype == np.uint8 and obs["prompt"] == "reach"
        return np.zeros((4, 2), np.float32)


def test_chunked_server_and_n_action_steps():
    env = get_task("point-reach").make_env()
    with PolicyServer(GoalChunks) as server:
        pol = RemotePolicy(server.url, timeout_s=5, n_action_steps=2, prompt="reach")
        out = run_episode(env, pol, init_state=0, seed=0)
        assert (out.success, out.steps) == (True, 12)
        assert server.n_requests == 6 and pol.chunk_size == 4  # 12 steps / 2 executed per chunk
        pol.close()


class Crashing:
    def reset(self):
        pass

    def select_action(self, obs):
        raise RuntimeError("boom in the model")


def test_server_side_error_is_a_policy_error():
    env = get_task("point-reach").make_env()
    with PolicyServer(Crashing) as server:
        pol = RemotePolicy(server.url, timeout_s=5, retries=2, backoff_s=0.01)
        with pytest.raises(PolicyError, match="boom in the model"):
            pol.select_action(env.reset(seed=0)[0])
        out = run_episode(env, pol, init_state=0, seed=0)
        assert out.status == "policy_error" and "boom in the model" in out.error


def test_unreachable_server_fails_after_bounded_retries():
    pol = RemotePolicy("ws://127.0.0.1:9", open_timeout_s=1, timeout_s=1, retries=2, backoff_s=0.05)
    t0 = time.monotonic()
    with pytest.raises(PolicyError, match="3 attempts: connection refused: nothing listens there"):
        pol.select_action({"agent_pos": np.zeros(2, np.float32)})
    assert time.monotonic() - t0 < 10
    once = RemotePolicy("ws://127.0.0.1:9", open_timeout_s=1, retries=0)
    with pytest.raises(PolicyError, match=r"unreachable after 1 attempt: connection refused"):
        once.select_action({"agent_pos": np.zeros(2, np.float32)})


def test_server_killed_mid_episode_ends_with_policy_error():
    proc = subprocess.Popen([sys.executable, "-m", "twinbench.policies.server", "--port", "0"],
                            stdout=subprocess.PIPE, text=True)
    try:
        line = proc.stdout.readline()  # "serving expert for point-reach on ws://127.0.0.1:PORT"
        url = line.strip().split()[-1]
        assert url.startswith("ws://127.0.0.1:"), line
        remote = RemotePolicy(url, open_timeout_s=1, timeout_s=1, retries=2, backoff_s=0.05)

        class KillAfter3:
            def __init__(self):
                self.n = 0

            def reset(self):
                remote.reset()

            def select_action(self, obs):
                self.n += 1
                if self.n == 4:
                    os.kill(proc.pid, signal.SIGKILL)
                    proc.wait(timeout=10)
                return remote.select_action(obs)

        env = get_task("point-reach").make_env()
        t0 = time.monotonic()
        out = run_episode(env, KillAfter3(), init_state=0, seed=0)
        assert (out.status, out.steps, out.success) == ("policy_error", 3, False)
        assert "unreachable after 3 attempts" in out.error and time.monotonic() - t0 < 15
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait(timeout=10)


class Hanging:
    release = threading.Event()

    def reset(self):
        pass

    def select_action(self, obs):
        Hanging.release.wait(20.0)  # far longer than the client's time-out, until the test lets it go
        return np.zeros(2, np.float32)


def test_silent_server_times_out():
    Hanging.release.clear()
    with PolicyServer(Hanging) as server:
        try:
            pol = RemotePolicy(server.url, timeout_s=0.3, retries=1, backoff_s=0.05)
            t0 = time.monotonic()
            with pytest.raises(PolicyError, match=r"2 attempts: no reply within the time-out of 0.3 s"):
                pol.select_action({"agent_pos": np.zeros(2, np.float32)})
            elapsed = time.monotonic() - t0
            # two time-outs and one backoff, not the server's answer (which never comes): a margin for a
            # loaded machine
            assert 0.6 <= elapsed < 10.0
        finally:
            Hanging.release.set()


class SlowFirst:
    """A model server whose first call compiles (1.0 s), later calls are quick."""

    calls = 0

    def reset(self):
        pass

    def select_action(self, obs):
        SlowFirst.calls += 1
        time.sleep(1.0 if SlowFirst.calls == 1 else 0.0)
        return np.zeros(2, np.float32)


def test_warm_up_waits_longer_once_then_calls_keep_their_time_out():
    obs = {"agent_pos": np.zeros(2, np.float32)}
    SlowFirst.calls = 0
    with PolicyServer(SlowFirst) as server:
        pol = RemotePolicy(server.url, timeout_s=0.3, retries=0, warm_up_timeout_s=5.0)
        pol.warm_up(obs)  # the 1 s first call fits the warm-up's time-out, not the 0.3 s per call
        assert SlowFirst.calls == 1 and (pol.timeout_s, pol.retries) == (0.3, 0)
        assert np.array_equal(pol.select_action(obs), [0, 0]) and SlowFirst.calls == 2
        pol.close()
    SlowFirst.calls = 0
    with PolicyServer(SlowFirst) as server:
        pol = RemotePolicy(server.url, timeout_s=0.3, retries=0)  # without warm-up: the first call fails
        with pytest.raises(PolicyError, match=r"no reply within the time-out of 0.3 s"):
            pol.select_action(obs)
        pol.close()


def test_timeout_from_the_spec():
    from twinbench.policies import make_policy, parse_policy_spec

    assert parse_policy_spec("remote:ws://h:1?timeout_s=90").timeout_s == 90.0
    for bad in ("remote:ws://h:1?timeout_s=0", "remote:ws://h:1?timeout_s=soon"):
        with pytest.raises(ValueError, match="timeout_s must be"):
            parse_policy_spec(bad)
    env = get_task("point-reach").make_env()
    pol = make_policy("remote:ws://127.0.0.1:9?timeout_s=2.5", get_task("point-reach"), env)
    assert pol.timeout_s == 2.5 and make_policy("remote:ws://127.0.0.1:9", get_task("point-reach"),
                                                env).timeout_s == 30.0
