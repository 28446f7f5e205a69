"""Client for policies served over websocket + msgpack (openpi's protocol).

On connect the server sends a metadata dict; each request is an observation dict (numpy arrays packed
by `policies.protocol`) and each reply a dict holding an `actions` chunk `(T, A)` (or `(A,)`). A text
frame as reply is the server's error report. Failures (refused connection, time-out, dropped
connection) are retried with exponential backoff; after `retries` retries the call raises
`PolicyError`. Worst case per call: (retries + 1) * (open_timeout_s + timeout_s) + backoffs.
A reply over `max_message_bytes` is refused (the connection is closed before it is read). A server that
refuses the API key (HTTP 401/403) fails at once, without retries. `timeout_s` (constructor, or
`?timeout_s=` in a `remote:` spec) bounds each reply; `warm_up(obs)` sends one request before the first
episode under the longer `warm_up_timeout_s` (a model server's first call compiles the model).

API key: `api_key=` or the TWINBENCH_API_KEY environment variable, sent as openpi's header
`Authorization: Api-Key <key>`. Close the policy (`close()`, or use it as a context manager) when done:
the connection is not closed from `__del__` during interpreter shutdown, where that could hang.
"""

from __future__ import annotations

import os
import sys
import time

import numpy as np

from twinbench.policies.base import ChunkedPolicy, PolicyError
from twinbench.policies.protocol import (
    ACTIONS_KEY,
    API_KEY_ENV,
    AUTH_HEADER,
    DEFAULT_MAX_MESSAGE_BYTES,
    USES_ENVIRONMENT_STATE_KEY,
    MessageError,
    api_key_value,
    packb,
    unpackb,
)


class RemotePolicy(ChunkedPolicy):
    """A policy behind `ws://HOST:PORT`; executes `n_action_steps` of each returned chunk (all if None).

    `io` (a `policies.io.PolicyIO`, set by `make_policy`): what the server is sent and how its reply
    becomes actions; None sends the observation as is (+ `prompt`) and executes the reply's `actions`.
    """

    io = None

    def __init__(self, url: str, *, timeout_s: float = 30.0, open_timeout_s: float = 5.0, retries: int = 3,
                 backoff_s: float = 0.5, n_action_steps: int | None = None, prompt: str | None = None,
                 api_key: str | None = None, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
                 warm_up_timeout_s: float = 600.0):
        super().__init__(n_action_steps)
        if not url.startswith(("ws://", "wss://")):
            raise ValueError(f"remote policy url must start with ws:// or wss://, got {url!r}")
        if (retries < 0 or timeout_s <= 0 or open_timeout_s <= 0 or backoff_s < 0 or max_message_bytes < 1
                or warm_up_timeout_s <= 0):
            raise ValueError("RemotePolicy: need retries >= 0, timeout_s > 0, open_timeout_s > 0, "
                             "backoff_s >= 0, max_message_bytes >= 1, warm_up_timeout_s > 0")
        self.warm_up_timeout_s = float(warm_up_timeout_s)
        self.url, self.timeout_s, self.open_timeout_s = url, float(timeout_s), float(open_timeout_s)
        self.retries, self.backoff_s, self.prompt = int(retries), float(backoff_s), prompt
        self.max_message_bytes = int(max_message_bytes)
        self._api_key = os.environ.get(API_KEY_ENV) if api_key is None else api_key
        self.metadata: dict | None = None
        self._conn = None
        self.n_connects = 0

    def _connect(self) -> None:
        from websockets.sync.client import connect

        headers = {AUTH_HEADER: api_key_value(self._api_key)} if self._api_key else None
        self._conn = connect(self.url, open_timeout=self.open_timeout_s, close_timeout=1.0,
                             compression=None, max_size=self.max_message_bytes, max_queue=2, proxy=None,
                             legacy=True, additional_headers=headers)
        self.n_connects += 1
        meta = self._conn.recv(timeout=self.timeout_s)
        if isinstance(meta, str):
            raise PolicyError(f"policy server {self.url} sent an error instead of metadata: {meta}")
        self.metadata = self._unpack(meta)

    def _unpack(self, data: bytes):
        try:
            return unpackb(data)
        except MessageError as err:
            self._drop()
            raise PolicyError(f"policy server {self.url} sent a malformed reply: {err}") from None

    def _drop(self) -> None:
        if self._conn is not None:
            try:
                self._conn.close()
            except Exception:  # noqa: BLE001 - the connection is being discarded anyway
                pass
        self._conn = None

    def infer(self, obs: dict) -> dict:
        """One request/reply round trip (reconnecting as needed); returns the server's reply dict."""
        from websockets.exceptions import (
            ConnectionClosed,
            InvalidHandshake,
            InvalidStatus,
            InvalidURI,
            WebSocketException,
        )

        payload = packb(obs)
        if len(payload) > self.max_message_bytes:
            raise PolicyError(f"observation of {len(payload)} bytes exceeds max_message_bytes="
                              f"{self.max_message_bytes}")
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
            except InvalidStatus as err:
                status = err.response.status_code
                self._drop()
                if status in (401, 403):
                    raise PolicyError(f"policy server {self.url} refused the API key (HTTP {status}); set "
                                      f"{API_KEY_ENV} to the server's key") from None
                last = err
                continue
            except ConnectionClosed as err:
                self._drop()
                by_server = err.rcvd is not None and (err.sent is None or err.rcvd_then_sent)
                if by_server and err.rcvd.code == 1009:
                    raise PolicyError(f"policy server {self.url} refused an observation of {len(payload)} "
                                      "bytes as too big (raise the server's max_message_bytes)") from None
                if not by_server and err.sent is not None and err.sent.code == 1009:
                    raise PolicyError(f"policy server {self.url} sent a reply over max_message_bytes="
                                      f"{self.max_message_bytes}") from None
                last = err
                continue
            except (OSError, TimeoutError, InvalidHandshake, WebSocketException, EOFError) as err:
                last = err
                self._drop()
                continue
            if isinstance(reply, str):
                self._drop()
                raise PolicyError(f"policy server {self.url} reported an error: {reply}")
            out = self._unpack(reply)
            if not isinstance(out, dict) or ACTIONS_KEY not in out:
                raise PolicyError(f"policy server {self.url} replied without an {ACTIONS_KEY!r} entry: "
                                  f"{type(out).__name__} {list(out) if isinstance(out, dict) else ''}")
            return out
        n = self.retries + 1
        if isinstance(last, ConnectionRefusedError):
            why = "connection refused: nothing listens there; start the server, or check the host and port"
        elif isinstance(last, TimeoutError):
            why = f"no reply within the time-out of {self.timeout_s} s"
        else:
            why = f"{type(last).__name__}: {last} (time-out {self.timeout_s} s)"
        raise PolicyError(f"policy server {self.url} unreachable after {n} attempt{'s' * (n != 1)}: {why}")

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
        return bool(self.metadata.get(USES_ENVIRONMENT_STATE_KEY, False))

    def warm_up(self, obs: dict | None = None) -> None:
        """Before the first episode: connect and, given an observation, send it once (reply discarded),
        waiting up to `warm_up_timeout_s` (no retries: a server that fails here fails the same way later)."""
        timeout, retries = self.timeout_s, self.retries
        self.timeout_s, self.retries = max(self.timeout_s, self.warm_up_timeout_s), 0
        try:
            if obs is None:
                if self._conn is None:
                    self._connect()
            else:
                self._request(obs)
        finally:
            self.timeout_s, self.retries = timeout, retries

    def _request(self, obs: dict) -> np.ndarray:
        if self.io is not None:  # per-policy observation mapping and action handling (policies.io)
            reply = self.infer(self.io.request(obs, self.prompt))
            if self.io.action.key not in reply:
                raise PolicyError(f"policy server {self.url} replied without {self.io.action.key!r}: "
                                  f"{sorted(reply)}")
            return self.io.actions(reply[self.io.action.key], obs)
        request = dict(obs)
        if self.prompt is not None:
            request.setdefault("prompt", self.prompt)
        return np.asarray(self.infer(request)[ACTIONS_KEY])

    def predict_chunk(self, obs: dict) -> np.ndarray:
        return self._request(obs)

    def finish_action(self, action: np.ndarray, obs: dict) -> np.ndarray:
        return action if self.io is None else self.io.step(action, obs)

    def close(self) -> None:
        """Close the connection (the next request reconnects)."""
        self._drop()

    def __enter__(self) -> RemotePolicy:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __del__(self):
        # Closing joins the connection's reader thread: never attempt it during interpreter shutdown.
        if not sys.is_finalizing():
            self._drop()
