"""A scripted expert served over websocket acts from the observation it is sent (environment_state
included because the server's metadata asks for it), exactly as the same expert run locally."""

import subprocess
import sys

import numpy as np

from twinbench.evaluation.rollout import run_episode
from twinbench.policies.remote import RemotePolicy
from twinbench.policies.server import PolicyServer
from twinbench.tasks import get_task


class Recorder:
    def __init__(self, policy):
        self.policy, self.actions = policy, []
        self.uses_environment_state = policy.uses_environment_state

    def reset(self):
        self.policy.reset()

    def select_action(self, obs):
        self.actions.append(np.asarray(self.policy.select_action(obs)))
        return self.actions[-1]


def test_served_push_t_expert_matches_the_local_one(fast_env):
    task = get_task("push-t")
    local = Recorder(task.make_expert(fast_env))
    run_episode(fast_env, local, init_state=5, seed=5, max_steps=6)
    meta = {"uses_environment_state": True}
    with PolicyServer(lambda: task.make_expert(fast_env), metadata=meta) as server:
        remote = RemotePolicy(server.url, timeout_s=10, retries=0)
        assert remote.uses_environment_state  # read from the metadata (connects once)
        rec = Recorder(remote)
        out = run_episode(fast_env, rec, init_state=5, seed=5, max_steps=6)
        remote.close()
    assert out.status == "ok" and len(rec.actions) == len(local.actions) == 6
    assert np.allclose(rec.actions, local.actions, atol=1e-6)


def test_server_cli_env_kwargs_and_metadata():
    proc = subprocess.Popen([sys.executable, "-m", "twinbench.policies.server", "--port", "0",
                             "--env-kwargs", '{"fail_step": 3}'], stdout=subprocess.PIPE, text=True)
    try:
        url = proc.stdout.readline().strip().split()[-1]
        pol = RemotePolicy(url, timeout_s=10, retries=0)
        assert not pol.uses_environment_state
        assert pol.metadata == {"task": "point-reach", "policy": "expert", "uses_environment_state": False}
        pol.close()
    finally:
        proc.kill()
        proc.wait(timeout=10)
    bad = subprocess.run([sys.executable, "-m", "twinbench.policies.server", "--env-kwargs", "[1]"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode != 0 and "JSON object" in bad.stderr
