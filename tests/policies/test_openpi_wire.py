"""openpi's websocket protocol, both ways, against an independent implementation written here from the
protocol (not twinbench's): the server speaks first with its metadata, messages are msgpack with numpy
arrays as {b"__ndarray__": True, b"data", b"dtype", b"shape"}, and an error is a text frame holding the
traceback followed by close code 1011."""

import threading
import traceback

import numpy as np
import pytest
from openpi_codec import pack, unpack
from served import CHUNK, Doubler, check_libero_exchange
from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect
from websockets.sync.server import serve

from twinbench.policies.server import PolicyServer


class OpenpiStyleServer:
    """A LIBERO-like openpi server: checks the request's keys and shapes, answers CHUNK."""

    def __init__(self):
        self.requests = []
        self._server = serve(self._handle, "127.0.0.1", 0, compression=None, max_size=None)
        self.url = f"ws://127.0.0.1:{self._server.socket.getsockname()[1]}"
        threading.Thread(target=self._server.serve_forever, daemon=True).start()

    def _handle(self, ws):
        ws.send(pack({"server": "openpi-style"}))
        while True:
            try:
                obs = unpack(ws.recv())
            except ConnectionClosed:
                return
            try:
                self.requests.append(obs)
                if obs["prompt"] == "crash":
                    raise RuntimeError("model exploded")
                assert obs["observation/image"].shape == (224, 224, 3)
                assert obs["observation/state"].shape == (8,)
                ws.send(pack({"actions": CHUNK, "server_timing": {"infer_ms": 1.0}}))
            except Exception:
                ws.send(traceback.format_exc())
                ws.close(1011, "Internal server error. Traceback included in previous frame.")
                return

    def close(self):
        self._server.shutdown()


def test_twinbench_client_against_openpi_style_server():
    server = OpenpiStyleServer()
    try:
        check_libero_exchange(server.url, server.requests)
    finally:
        server.close()


def test_openpi_style_client_against_twinbench_server():
    with PolicyServer(Doubler, metadata={"policy": "doubler"}) as server:
        with connect(server.url, compression=None, max_size=None) as ws:
            meta = ws.recv()
            assert isinstance(meta, bytes) and unpack(meta) == {"policy": "doubler"}  # metadata first
            ws.send(pack({"agent_pos": np.array([0.25, -1.5], np.float32), "prompt": "go"}))
            reply = unpack(ws.recv())
            assert reply["actions"].dtype == np.float32 and reply["actions"].tolist() == [[0.5, -3.0]]
            ws.send(pack({"agent_pos": np.zeros(2, np.float32), "prompt": "crash"}))
            err = ws.recv()
            assert isinstance(err, str) and "ValueError: bad observation" in err
            with pytest.raises(ConnectionClosed) as closed:
                ws.recv()
            assert closed.value.rcvd.code == 1011
