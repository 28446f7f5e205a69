"""Policy server/client hardening (issue 14): sizes, connection limit, API key, error replies, shutdown."""

from __future__ import annotations

import os
import struct
import subprocess
import sys
import time

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosedError
from websockets.sync.client import connect

from twinbench.policies import PolicyError
from twinbench.policies.protocol import API_KEY_ENV, MessageError, packb, unpackb
from twinbench.policies.remote import RemotePolicy
from twinbench.policies.server import PolicyServer, public_error
from twinbench.tasks.point_reach import PointReachExpert

OBS = {"agent_pos": np.zeros(2, np.float32)}


@pytest.fixture(autouse=True)
def _no_key_from_the_environment(monkeypatch):
    monkeypatch.delenv(API_KEY_ENV, raising=False)


def _raw(url, **kw):
    return connect(url, compression=None, max_size=None, proxy=None, open_timeout=5, legacy=True, **kw)


def test_defaults_bind_loopback():
    with PolicyServer(PointReachExpert) as server:
        assert server.host == "127.0.0.1" and not server.requires_api_key


def test_a_frame_over_the_limit_closes_the_connection_before_its_payload_arrives():
    with PolicyServer(PointReachExpert, max_message_bytes=2**20) as server:
        ws = _raw(server.url)
        ws.recv(timeout=5)  # metadata
        # a masked binary frame header announcing 1 GiB, followed by 4 bytes: the server must not wait for
        # (or buffer) the rest
        ws.socket.sendall(bytes([0x82, 0xFF]) + struct.pack(">Q", 2**30) + b"mask" + b"abcd")
        t0 = time.monotonic()
        with pytest.raises(ConnectionClosedError) as err:
            ws.recv(timeout=5)
        assert err.value.rcvd.code == 1009 and time.monotonic() - t0 < 2
        ws.close()
        with RemotePolicy(server.url, timeout_s=5) as ok:  # the server still serves
            assert ok.infer(OBS)["actions"].shape == (1, 2)
        with RemotePolicy(server.url, timeout_s=5, retries=0) as big:
            with pytest.raises(PolicyError, match="too big"):
                big.infer({"img": np.zeros(2**21, np.uint8)})


def test_a_message_of_millions_of_tiny_arrays_is_refused():
    n = 200_000
    body = b"\xdd" + struct.pack(">I", n) + packb(np.zeros(0)) * n  # a list of 200k empty arrays, 9 MB
    with pytest.raises(MessageError, match="100000"):
        unpackb(body)
    with PolicyServer(PointReachExpert) as server:
        ws = _raw(server.url)
        ws.recv(timeout=5)
        ws.send(body)
        reply = ws.recv(timeout=5)
        assert reply.startswith("bad request: MessageError") and "100000" in reply
        ws.close()


def test_msgpack_refuses_dtypes_and_shapes_that_are_not_plain_arrays():
    ok = packb(np.arange(6, dtype=np.int16).reshape(2, 3))
    np.testing.assert_array_equal(unpackb(ok), np.arange(6).reshape(2, 3))
    bad = [
        {b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "O", b"shape": [1]},
        {b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "(1000000000,)f8", b"shape": [1]},
        {b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "<f4", b"shape": [3]},
        {b"__ndarray__": True, b"data": b"\0" * 8, b"dtype": "<f4", b"shape": [-1]},
        {b"__ndarray__": True, b"dtype": "<f4", b"shape": [2]},
        {b"__npgeneric__": True, b"data": "x", b"dtype": "<f4"},
    ]
    import msgpack

    for obj in bad:
        with pytest.raises(MessageError):
            unpackb(msgpack.packb(obj, use_bin_type=True))
    for junk in (b"\xc1", b"\x92\x01", b"\x91" * 5000, "text"):
        with pytest.raises(MessageError):
            unpackb(junk)


def test_connection_limit():
    with PolicyServer(PointReachExpert, max_connections=2) as server:
        a, b = RemotePolicy(server.url, timeout_s=5), RemotePolicy(server.url, timeout_s=5)
        a.infer(OBS)
        b.infer(OBS)
        c = RemotePolicy(server.url, timeout_s=5, retries=0)
        with pytest.raises(PolicyError, match="503"):
            c.infer(OBS)
        a.close()
        time.sleep(0.2)  # the server notices the close
        assert c.infer(OBS)["actions"].shape == (1, 2)
        b.close()
        c.close()
        assert server.n_rejected == 1


def test_api_key(monkeypatch):
    with PolicyServer(PointReachExpert, api_key="s3cret") as server:
        assert server.requires_api_key
        for key in (None, "wrong"):
            pol = RemotePolicy(server.url, timeout_s=5, retries=3, backoff_s=1.0, api_key=key)
            t0 = time.monotonic()
            with pytest.raises(PolicyError, match=r"refused the API key \(HTTP 401\)"):
                pol.infer(OBS)
            assert time.monotonic() - t0 < 1  # no retries for a refused key
        with RemotePolicy(server.url, timeout_s=5, api_key="s3cret") as pol:
            assert pol.infer(OBS)["actions"].shape == (1, 2)
        monkeypatch.setenv(API_KEY_ENV, "s3cret")  # the client reads it from the environment too
        with RemotePolicy(server.url, timeout_s=5) as pol:
            assert pol.infer(OBS)["actions"].shape == (1, 2)
        # openpi's client sends exactly this header
        ws = _raw(server.url, additional_headers={"Authorization": "Api-Key s3cret"})
        assert unpackb(ws.recv(timeout=5)) == {}
        ws.close()


class LeakyPolicy:
    def reset(self):
        pass

    def select_action(self, obs):
        raise FileNotFoundError("/home/alice/secret_project/ckpt/model.safetensors not found")


def test_error_replies_carry_no_traceback_and_no_paths():
    with PolicyServer(LeakyPolicy) as server:
        pol = RemotePolicy(server.url, timeout_s=5, retries=0)
        with pytest.raises(PolicyError) as err:
            pol.infer(OBS)
    msg = str(err.value)
    assert "policy error: FileNotFoundError: <path> not found" in msg
    assert "alice" not in msg and "Traceback" not in msg and 'File "' not in msg and ".py" not in msg
    assert public_error(ValueError(r"bad C:\Users\bob\x.ckpt or /opt/m/w.bin")) == \
        "ValueError: bad <path> or <path>"


def test_idle_clients_are_dropped_and_the_client_reconnects():
    with PolicyServer(PointReachExpert, idle_timeout_s=0.3) as server:
        with RemotePolicy(server.url, timeout_s=5) as pol:
            pol.infer(OBS)
            time.sleep(0.8)
            assert pol.infer(OBS)["actions"].shape == (1, 2)
            assert pol.n_connects == 2


class BigChunks:
    def reset(self):
        pass

    def predict_chunk(self, obs):
        return np.zeros((2**18, 2), np.float32)  # 2 MiB


def test_client_limits_the_size_of_replies():
    with PolicyServer(BigChunks) as server:
        with RemotePolicy(server.url, timeout_s=5, max_message_bytes=2**20) as pol:
            with pytest.raises(PolicyError, match="reply over max_message_bytes"):
                pol.infer(OBS)
        with RemotePolicy(server.url, timeout_s=5) as pol:
            assert pol.infer(OBS)["actions"].shape == (2**18, 2)


def test_eval_in_process_against_a_remote_policy_exits(tmp_path):
    with PolicyServer(PointReachExpert) as server:
        cmd = [sys.executable, "-m", "twinbench.cli", "eval", "--run-id", "rem", "--task", "point-reach",
               "--policy", f"remote:{server.url}", "--episodes", "grid:0", "--workers", "0",
               "--db", str(tmp_path / "r.sqlite"), "--output-dir", str(tmp_path), "--no-progress"]
        res = subprocess.run(cmd, capture_output=True, text=True, timeout=60,
                             env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert res.returncode == 0, res.stderr
    assert "1/1 successes" in res.stderr


STUCK_PREFIXES = {  # what a client sends before going silent; the buffer is empty once a header is read
    "one header byte": bytes([0x82]),
    "a two-byte header": bytes([0x82, 0xFE]),
    "a whole header": bytes([0x82, 0xFE]) + struct.pack(">H", 1000) + b"mask",
    "a first fragment": bytes([0x02, 0x83]) + bytes(4) + b"abc",  # not final, masked with zeros
}


@pytest.mark.parametrize("prefix", STUCK_PREFIXES.values(), ids=STUCK_PREFIXES.keys())
def test_a_begun_message_that_stops_falls_under_the_read_deadline_not_the_idle_one(prefix):
    with PolicyServer(PointReachExpert, read_timeout_s=0.5, idle_timeout_s=60) as server:
        stuck, idle = _raw(server.url), _raw(server.url)
        stuck.recv(timeout=5)
        idle.recv(timeout=5)
        stuck.socket.sendall(prefix)
        t0 = time.monotonic()
        with pytest.raises(ConnectionClosedError) as err:
            stuck.recv(timeout=10)
        assert err.value.rcvd.code == 1008 and time.monotonic() - t0 < 3
        idle.send(packb(OBS))  # a connection that began nothing is kept
        assert unpackb(idle.recv(timeout=5))["actions"].shape == (1, 2)
        stuck.close()
        idle.close()
