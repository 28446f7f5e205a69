"""openpi's own code against twinbench, both ways: its client package (`openpi-client`, PyPI: what a user of
openpi's examples already has) against twinbench's policy server, and twinbench's `remote:` client against
openpi's `WebsocketPolicyServer` (as packaged on PyPI by `openpi-server`, which needs openpi-client). Skipped
where they are not installed; CI's numpy-1 job installs both (openpi and openpi-client require numpy < 2, see
.ci/run)."""

import socket
import threading
import time

import numpy as np
import pytest
from served import CHUNK, Doubler, check_libero_exchange

from twinbench.evaluation.rollout import policy_observation
from twinbench.policies.server import PolicyServer
from twinbench.policies.spec import make_policy
from twinbench.tasks import get_task

openpi_client = pytest.importorskip("openpi_client.websocket_client_policy")
# openpi-client 0.1.2 opens its connection without a context manager, which newer websockets flag
pytestmark = pytest.mark.filterwarnings("ignore:connect\\(\\) must be used:DeprecationWarning")


def test_openpi_client_talks_to_twinbench_server():
    with PolicyServer(Doubler, metadata={"policy": "doubler"}, api_key="k3y") as server:
        client = openpi_client.WebsocketClientPolicy(server.url, api_key="k3y")
        assert client.get_server_metadata() == {"policy": "doubler"}
        reply = client.infer({"agent_pos": np.array([0.25, -1.5], np.float32), "prompt": "go"})
        assert reply["actions"].dtype == np.float32 and reply["actions"].tolist() == [[0.5, -3.0]]
        with pytest.raises(RuntimeError, match="ValueError: bad observation"):
            client.infer({"agent_pos": np.zeros(2, np.float32), "prompt": "crash"})
        with pytest.raises(Exception):  # noqa: B017 - a wrong key is refused before the websocket opens
            openpi_client.WebsocketClientPolicy(server.url, api_key="wrong")


def test_openpi_client_drives_the_served_expert():
    """`twinbench serve`'s setup (the task's expert, acting from the environment state it is sent) through
    openpi's client: its actions are the expert's own."""
    task = get_task("point-reach")
    env = task.make_env()
    with PolicyServer(lambda: make_policy("expert", task, env, seed=0)) as server:
        client = openpi_client.WebsocketClientPolicy(server.url)
        local = make_policy("expert", task, env, seed=0)
        obs, info = env.reset(seed=3)
        for _ in range(5):
            sent = policy_observation(local, obs, info)  # with the privileged environment_state
            remote = np.asarray(client.infer(sent)["actions"])[0]
            want = np.asarray(local.select_action(sent))
            assert np.allclose(remote, want, atol=1e-6)
            obs, _, _, _, info = env.step(want)


class LiberoModel:
    """An openpi policy (`infer(obs) -> dict`) answering CHUNK to LIBERO-shaped requests."""

    def __init__(self):
        self.requests = []

    def infer(self, obs):
        self.requests.append(obs)
        if obs["prompt"] == "crash":
            raise RuntimeError("model exploded")
        assert obs["observation/image"].shape == (224, 224, 3) and obs["observation/state"].shape == (8,)
        return {"actions": CHUNK}

    def reset(self):
        pass


def test_twinbench_client_against_openpis_own_server():
    server_mod = pytest.importorskip("openpi_server.websocket_policy_server")
    with socket.socket() as s:  # a free port (openpi's server does not report the one it binds)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    model = LiberoModel()
    server = server_mod.WebsocketPolicyServer(model, host="127.0.0.1", port=port, metadata={"env": "libero"})
    threading.Thread(target=server.serve_forever, daemon=True).start()
    for _ in range(200):  # until it listens
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        time.sleep(0.05)
    check_libero_exchange(f"ws://127.0.0.1:{port}", model.requests)
