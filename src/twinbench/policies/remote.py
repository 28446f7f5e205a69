"""Client for policies served over websocket + msgpack (openpi's protocol).

On connect the server sends a metadata dict; each request is an observation dict (numpy arrays packed
by `msgpack_numpy`) and each reply a dict holding an `actions` chunk `(T, A)` (or `(A,)`). A text
frame as reply is the server's error report. Failures (refused connection, time-out, dropped
connection) are retried with exponential backoff; after `retries` retries the call raises
`PolicyError`. Worst case per call: (retries + 1) * (open_timeout_s + timeout_s) + backoffs.
"""

from __future__ import annotations

import time

import numpy as np

from twinbench.policies.base import ChunkedPolicy, PolicyError
from twinbench.policies.msgpack_numpy import packb, unpackb


class RemotePolicy(ChunkedPolicy):
    """A policy behind `ws://HOST:PORT`; executes `n_action_steps` of each returned chunk (all if None).

    `io` (a `policies.io.PolicyIO`, set by `make_policy`): what the server is sent and how its reply
    becomes actions; None sends the observation as is (+ `prompt`) and executes the reply's `actions`.
    """

    io = None

    def __init__(self, url: str, *, timeout_s: float = 30.0, open_timeout_s: float = 5.0, retries: int = 3,
                 backoff_s: float = 0.5, n_action_steps: int | None = None, prompt: str | None = None):
        super().__init__(n_action_steps)
        if not url.startswith(("ws://", "wss://")):
            raise ValueError(f"remote policy url must start with ws:// or wss://, got {url!r}")
        if retries < 0 or timeout_s <= 0 or open_timeout_s <= 0 or backoff_s < 0:
            raise ValueError("RemotePolicy: need retries >= 0, timeout_s > 0, open_timeout_s > 0, "
                             "backoff_s >= 0")
        self.url, self.timeout_s, self.open_timeout_s = url, float(timeout_s), float(open_timeout_s)
        self.retries, self.backoff_s, self.prompt = int(retries), float(backoff_s), prompt
        self.metadata: dict | None = None
        self._conn = None
        self.n_connects = 0

    def _connect(self) -> None:
        from websockets.sync.client import connect

        self._conn = connect(self.url, open_timeout=self.open_timeout_s, close_timeout=1.0,
                             compression=None, max_size=None, proxy=None, legacy=True)
        self.n_connects += 1
        meta = self._conn.recv(timeout=self.timeout_s)
        if isinstance(meta, str):
            raise PolicyError(f"policy server {self.url} sent an error instead of metadata:\n{meta}")
        self.metadata = unpackb(meta)

    def _drop(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # noqa: BLE001 - the connection is being discarded anyway
                pass
        self._conn = None

    def infer(self, obs: dict) -> dict:
        """One request/reply round trip (reconnecting as needed); returns the server's reply dict."""
        from websockets.exceptions import InvalidHandshake, InvalidURI, WebSocketException

        payload = packb(obs)
        last: BaseException | None = None
        for attempt in range(self.retries + 1):
            if attempt:
                time.sleep(self.backoff_s * 2 ** (attempt - 1))
            try:
                if self._conn is None:
                    self._connect()
                self._conn.send(payload)
                reply = self._conn.recv(timeout=self.timeout_s)
            except InvalidURI as err:
                raise PolicyError(f"bad policy server url {self.url!r}: {err}") from err
            except (OSError, TimeoutError, InvalidHandshake, WebSocketException, EOFError) as err:
                last = err
                self._drop()
                continue
            if isinstance(reply, str):
                self._drop()
                raise PolicyError(f"policy server {self.url} reported an error:\n{reply}")
            out = unpackb(reply)
            if not isinstance(out, dict) or "actions" not in out:
                raise PolicyError(f"policy server {self.url} replied without an 'actions' entry: "
                                  f"{type(out).__name__} {list(out) if isinstance(out, dict) else ''}")
            return out
        raise PolicyError(f"policy server {self.url} unreachable after {self.retries + 1} attempts "
                          f"(time-out {self.timeout_s} s): {type(last).__name__}: {last}")

    @property
    def uses_environment_state(self) -> bool:
        """Whether the served policy acts from the privileged `environment_state` (a scripted expert's
        server says so in its metadata): the runner then sends it with each observation."""
        if self.metadata is None:
            try:
                self._connect()
            except Exception:  # noqa: BLE001 - the failure is reported by the first select_action
                self._drop()
                return False
        return bool(self.metadata.get("uses_environment_state", False))

    def predict_chunk(self, obs: dict) -> np.ndarray:
        if self.io is not None:  # per-policy observation mapping and action handling (policies.io)
            reply = self.infer(self.io.request(obs, self.prompt))
            if self.io.action.key not in reply:
                raise PolicyError(f"policy server {self.url} replied without {self.io.action.key!r}: "
                                  f"{sorted(reply)}")
            return self.io.actions(reply[self.io.action.key], obs)
        request = dict(obs)
        if self.prompt is not None:
            request.setdefault("prompt", self.prompt)
        return np.asarray(self.infer(request)["actions"])

    def close(self) -> None:
        self._drop()

    def __del__(self):
        self._drop()
