"""Minimal websocket + msgpack policy server (openpi's protocol) serving any local policy.

    python -m twinbench.policies.server --task point-reach --policy expert@0.2 --port 8000

Each connection gets its own policy instance (from `make_policy()`), is sent `metadata` first, then
every binary message (a packed observation) is answered with `{"actions": (T, A) array}`: the
policy's `predict_chunk` when it has one, else its `select_action` as a chunk of one. An exception is
reported to the client as a text frame holding the traceback, then the connection is closed.
Binds 127.0.0.1 by default.
"""

from __future__ import annotations

import threading
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from twinbench.policies.msgpack_numpy import packb, unpackb


def _predict(policy, obs: dict) -> np.ndarray:
    if hasattr(policy, "predict_chunk"):
        return np.asarray(policy.predict_chunk(obs))
    return np.asarray(policy.select_action(obs))[None]


class PolicyServer:
    """Serve `make_policy()` policies on ws://host:port (port 0 = pick a free one)."""

    def __init__(self, make_policy: Callable[[], object], *, host: str = "127.0.0.1", port: int = 0,
                 metadata: dict | None = None):
        from websockets.sync.server import serve

        self.make_policy, self.metadata = make_policy, dict(metadata or {})
        self.n_requests = 0
        self._server = serve(self._handle, host, port, compression=None, max_size=None)
        self.host, self.port = self._server.socket.getsockname()[:2]
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def _handle(self, ws) -> None:
        policy = self.make_policy()
        if hasattr(policy, "reset"):
            policy.reset()
        ws.send(packb(self.metadata))
        for message in ws:
            try:
                t0 = time.perf_counter()
                obs = unpackb(message)
                actions = _predict(policy, obs)
                self.n_requests += 1
                timing = {"infer_ms": 1e3 * (time.perf_counter() - t0)}
                ws.send(packb({"actions": actions, "server_timing": timing}))
            except Exception:  # noqa: BLE001 - reported to the client, which raises PolicyError
                ws.send(traceback.format_exc())
                ws.close(1011, "policy error")
                return

    def serve_forever(self) -> None:
        self._server.serve_forever()

    def start(self) -> PolicyServer:
        """Serve from a daemon thread; returns self."""
        self._thread = threading.Thread(target=self.serve_forever, daemon=True)
        self._thread.start()
        return self

    def close(self) -> None:
        self._server.shutdown()
        if self._thread is not None:
            self._thread.join(timeout=5)

    def __enter__(self) -> PolicyServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.close()


@dataclass(frozen=True)
class ServeConfig:
    """Serve a local policy (spec string, e.g. expert or expert@0.3) of a task over websocket."""

    task: str = "point-reach"
    policy: str = "expert"
    host: str = "127.0.0.1"
    port: int = 8000
    seed: int = 0
    env_kwargs: str = ""  # JSON object of env constructor arguments, as `twinbench eval --env-kwargs`


def main(cfg: ServeConfig) -> int:
    from twinbench.policies.spec import make_policy, parse_policy_spec
    from twinbench.tasks import get_task

    task = get_task(cfg.task)
    spec = parse_policy_spec(cfg.policy)
    if spec.kind == "remote":
        raise ValueError("--policy: the server serves local policies (expert, expert@LEVEL, lerobot:PATH)")
    from twinbench.cli import quiet_warp
    from twinbench.evaluation.runner import parse_env_kwargs

    quiet_warp()  # the printed url is the first stdout line

    env = task.make_env(**parse_env_kwargs(cfg.env_kwargs))
    # A scripted expert acts from the environment_state it is sent (the metadata tells the client).
    uses_state = bool(getattr(make_policy(spec, task, env, seed=cfg.seed), "uses_environment_state", False))
    server = PolicyServer(lambda: make_policy(spec, task, env, seed=cfg.seed), host=cfg.host, port=cfg.port,
                          metadata={"task": cfg.task, "policy": cfg.policy,
                                    "uses_environment_state": uses_state})
    print(f"serving {cfg.policy} for {cfg.task} on {server.url}", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        server.close()
    return 0


if __name__ == "__main__":
    import tyro

    raise SystemExit(main(tyro.cli(ServeConfig)))
