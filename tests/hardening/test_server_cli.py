"""The policy server under bad options and slow clients (issue 25): each bad option is one line naming it,
exit code 2; clients that begin a message and trickle it are dropped after the read time-out, so they
cannot lock a legitimate client out."""

from __future__ import annotations

import struct
import threading
import time

import numpy as np
import pytest
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

from twinbench.cli import main as cli
from twinbench.policies import PolicyError
from twinbench.policies.protocol import API_KEY_ENV
from twinbench.policies.remote import RemotePolicy
from twinbench.policies.server import PolicyServer
from twinbench.tasks.point_reach import PointReachExpert

OBS = {"agent_pos": np.zeros(2, np.float32)}

CASES = [
    (["--max-connections", "0"], "--max-connections 0: must be in [1, 1024]"),
    (["--max-connections", "100000"], "--max-connections 100000"),
    (["--max-message-bytes", "-1"], "--max-message-bytes -1: must be in"),
    (["--idle-timeout-s", "0"], "--idle-timeout-s 0.0: must be in"),
    (["--idle-timeout-s", "nan"], "--idle-timeout-s nan"),
    (["--read-timeout-s", "0"], "--read-timeout-s 0.0: must be in"),
    (["--read-timeout-s", "inf"], "--read-timeout-s inf: must be in"),
    (["--port", "70000"], "--port 70000: must be in [0, 65535]"),
    (["--port", "-1"], "--port -1"),
    (["--host", "no.such.host.invalid"], "--host 'no.such.host.invalid': not an address"),
    (["--host", "192.0.2.1"], "--host 192.0.2.1 --port 0: cannot listen there"),
    (["--env-kwargs", "{oops"], "--env-kwargs must be a JSON object"),
    (["--env-kwargs", "[1, 2]"], "--env-kwargs must be a JSON object"),
    (["--policy", "remote:ws://127.0.0.1:1"], "--policy: the server serves local policies"),
]


@pytest.mark.parametrize(("args", "needle"), CASES, ids=[" ".join(a) for a, _ in CASES])
def test_bad_serve_options_are_one_line_and_exit_code_2(capsys, args, needle):
    argv = ["serve", "--port", "0", *args] if "--port" not in args else ["serve", *args]
    assert cli(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("twinbench serve: error: ") and needle in err[0], err


def test_read_timeout_must_be_finite_and_positive():
    for bad in (0.0, -1.0, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="read_timeout_s"):
            PolicyServer(PointReachExpert, read_timeout_s=bad)


def test_slow_senders_are_dropped_and_do_not_lock_out_a_client(monkeypatch):
    monkeypatch.delenv(API_KEY_ENV, raising=False)
    stop = threading.Event()
    codes: list[int | None] = []

    def slow_sender(url):
        ws = connect(url, compression=None, max_size=None, proxy=None, open_timeout=10, legacy=True)
        ws.recv(timeout=10)  # metadata
        try:  # a masked binary frame of 1000 bytes, sent one byte every 0.2 s (200 s in all)
            ws.socket.sendall(bytes([0x82, 0xFE]) + struct.pack(">H", 1000) + b"mask")
            while not stop.is_set():
                ws.socket.sendall(b"x")
                time.sleep(0.2)
        except OSError:
            pass
        try:
            ws.recv(timeout=10)
        except ConnectionClosed as err:
            codes.append(err.rcvd.code if err.rcvd else None)
        except (TimeoutError, OSError):
            codes.append(None)
        ws.close()

    with PolicyServer(PointReachExpert, max_connections=16, read_timeout_s=1.0) as server:
        threads = [threading.Thread(target=slow_sender, args=(server.url,), daemon=True) for _ in range(16)]
        for t in threads:
            t.start()
        time.sleep(0.5)
        with pytest.raises(PolicyError, match="503"):  # all 16 connections are taken now
            RemotePolicy(server.url, timeout_s=5, retries=0).infer(OBS)
        t0, served = time.monotonic(), None
        while served is None and time.monotonic() - t0 < 20:
            try:
                with RemotePolicy(server.url, timeout_s=5, retries=0) as pol:
                    served = pol.infer(OBS)["actions"]
            except PolicyError:
                time.sleep(0.2)
        waited = time.monotonic() - t0
        stop.set()
        for t in threads:
            t.join(timeout=15)
    assert served is not None and served.shape == (1, 2) and waited < 10, waited
    assert codes.count(1008) == 16, codes  # each slow sender was closed for its slowness
