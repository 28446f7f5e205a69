"""Minimal websocket + msgpack policy server (openpi's protocol, `policies.protocol`) serving any local
policy.

    twinbench serve --task point-reach --policy expert@0.2 --port 8000

(`python -m twinbench.policies.server ...` is an alias of `twinbench serve ...`.)

Each connection gets its own policy instance (from `make_policy()`), is sent `metadata` first, then
every binary message (a packed observation) is answered with `{"actions": (T, A) array}`: the
policy's `predict_chunk` when it has one, else its `select_action` as a chunk of one. A failure is
reported to the client as one text frame, "policy error: TYPE: message" (no traceback, file paths
replaced by <path>; the full traceback goes to this process's log), then the connection is closed.

Limits (all configurable): binds 127.0.0.1 by default; messages over `max_message_bytes` close the
connection (code 1009) before they are read; at most `max_connections` clients at once (more get HTTP
503); an idle client is dropped after `idle_timeout_s`, and one that has begun a message (a frame's
header is a beginning) but not sent all of it within `read_timeout_s` (a slow sender holding a connection)
too; with an `api_key` (or TWINBENCH_API_KEY set) every client must send openpi's header
`Authorization: Api-Key <key>` (else HTTP 401).
"""

from __future__ import annotations

import hmac
import http
import logging
import os
import re
import sys
import threading
import time
from collections.abc import Callable

import numpy as np

from twinbench.policies.protocol import (
    ACTIONS_KEY,
    API_KEY_ENV,
    AUTH_HEADER,
    DEFAULT_MAX_MESSAGE_BYTES,
    TIMING_KEY,
    MessageError,
    api_key_value,
    packb,
    unpackb,
)

DEFAULT_MAX_CONNECTIONS = 16
DEFAULT_IDLE_TIMEOUT_S = 600.0
DEFAULT_READ_TIMEOUT_S = 30.0  # from a message's first byte to its last
_POLL_S = 0.25  # how often a waiting connection looks for a message begun but not finished

log = logging.getLogger(__name__)
_PATH_RE = re.compile(r"(?:[A-Za-z]:)?(?:[\\/][^\s\\/'\":,()\[\]]+){2,}[\\/]?")


def public_error(err: BaseException) -> str:
    """'TYPE: message' with file paths replaced by <path>: what a remote client may see of an error."""
    text = f"{type(err).__name__}: {err}".strip()
    text = _PATH_RE.sub("<path>", text)
    return text if len(text) <= 2000 else text[:2000] + " ..."


def _partial_message(ws) -> bool:
    """Whether a message has begun to arrive but is not whole: unparsed bytes in the protocol's read
    buffer, a frame whose header was read but not its payload (the parser is inside `Frame.parse`, the
    buffer may be empty), or the first fragments of a fragmented message."""
    from websockets.frames import Frame

    protocol = getattr(ws, "protocol", None)
    reader = getattr(protocol, "reader", None)
    frames = getattr(getattr(ws, "recv_messages", None), "frames", None)
    gen, in_frame = getattr(protocol, "parser", None), False
    for _ in range(8):  # the chain of `yield from`: ServerProtocol.parse, Protocol.parse, Frame.parse, ...
        in_frame = in_frame or getattr(gen, "gi_code", None) is Frame.parse.__code__
        gen = getattr(gen, "gi_yieldfrom", None)
    return (bool(len(getattr(reader, "buffer", b""))) or in_frame
            or getattr(protocol, "current_size", None) is not None
            or (frames is not None and not frames.empty()))


def _fail_connection(ws, code: int, reason: str) -> None:
    """Send a close frame and end the TCP connection without waiting for the client's reply, which
    would be read as the rest of the frame it has begun (RFC 6455 7.1.7, "fail the connection")."""
    from websockets.exceptions import ConnectionClosed

    try:
        with ws.send_context():
            ws.protocol.fail(code, reason)
    except ConnectionClosed:
        pass


def _predict(policy, obs: dict) -> np.ndarray:
    if hasattr(policy, "predict_chunk"):
        return np.asarray(policy.predict_chunk(obs))
    return np.asarray(policy.select_action(obs))[None]


class PolicyServer:
    """Serve `make_policy()` policies on ws://host:port (port 0 = pick a free one).

    `api_key`: None reads TWINBENCH_API_KEY (unset or empty = no key required)."""

    def __init__(self, make_policy: Callable[[], object], *, host: str = "127.0.0.1", port: int = 0,
                 metadata: dict | None = None, max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES,
                 max_connections: int = DEFAULT_MAX_CONNECTIONS,
                 idle_timeout_s: float | None = DEFAULT_IDLE_TIMEOUT_S, api_key: str | None = None,
                 read_timeout_s: float = DEFAULT_READ_TIMEOUT_S):
        from websockets.sync.server import serve

        if int(max_message_bytes) < 1 or int(max_connections) < 1:
            raise ValueError("PolicyServer: max_message_bytes and max_connections must be >= 1")
        if idle_timeout_s is not None and not idle_timeout_s > 0:
            raise ValueError(f"PolicyServer: idle_timeout_s must be > 0 or None, got {idle_timeout_s}")
        if not 0 < read_timeout_s < float("inf"):
            raise ValueError(f"PolicyServer: read_timeout_s must be finite and > 0, got {read_timeout_s}")
        self.read_timeout_s = float(read_timeout_s)
        self.make_policy, self.metadata = make_policy, dict(metadata or {})
        self.max_message_bytes, self.max_connections = int(max_message_bytes), int(max_connections)
        self.idle_timeout_s = idle_timeout_s
        key = os.environ.get(API_KEY_ENV) if api_key is None else api_key
        self._auth = api_key_value(key).encode() if key else None
        self.n_requests = 0
        self.n_rejected = 0
        self._active = 0
        self._lock = threading.Lock()
        # max_queue=2: requests are answered one at a time, so a client cannot park many big frames here
        self._server = serve(self._handle, host, port, compression=None, max_size=self.max_message_bytes,
                             max_queue=2, process_request=self._process_request, open_timeout=10,
                             close_timeout=2)
        self.host, self.port = self._server.socket.getsockname()[:2]
        self._thread: threading.Thread | None = None

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    @property
    def requires_api_key(self) -> bool:
        return self._auth is not None

    def _process_request(self, connection, request):
        """HTTP-level checks before the websocket opens: API key, then the connection limit."""
        if self._auth is not None:
            sent = (request.headers.get(AUTH_HEADER) or "").encode()
            if not hmac.compare_digest(sent, self._auth):
                self.n_rejected += 1
                return connection.respond(http.HTTPStatus.UNAUTHORIZED,
                                          "missing or wrong 'Authorization: Api-Key <key>' header\n")
        with self._lock:
            full = self._active >= self.max_connections
        if full:
            self.n_rejected += 1
            return connection.respond(http.HTTPStatus.SERVICE_UNAVAILABLE,
                                      f"too many connections (limit {self.max_connections})\n")
        return None

    def _handle(self, ws) -> None:
        with self._lock:
            self._active += 1
            over = self._active > self.max_connections
        try:
            if over:  # two clients raced past _process_request
                self.n_rejected += 1
                ws.close(1013, "too many connections")
                return
            self._serve_connection(ws)
        finally:
            with self._lock:
                self._active -= 1

    def _fail(self, ws, prefix: str, err: BaseException, code: int) -> None:
        try:
            ws.send(f"{prefix}: {public_error(err)}")
            ws.close(code, prefix)
        except Exception:  # noqa: BLE001 - the client may already be gone
            pass

    def _serve_connection(self, ws) -> None:
        from websockets.exceptions import ConnectionClosed

        try:
            policy = self.make_policy()
            if hasattr(policy, "reset"):
                policy.reset()
        except Exception as err:  # noqa: BLE001 - reported to the client (without paths) and logged
            log.exception("building the policy failed")
            self._fail(ws, "policy error", err, 1011)
            return
        try:
            ws.send(packb(self.metadata))
            while True:
                message = self._receive(ws)
                if message is None:
                    return
                if isinstance(message, str):
                    self._fail(ws, "bad request", MessageError("text frame; send msgpack (binary) frames"),
                               1003)
                    return
                t0 = time.perf_counter()
                try:
                    obs = unpackb(message)
                    if not isinstance(obs, dict):
                        raise MessageError(f"an observation must be a map, got {type(obs).__name__}")
                except MessageError as err:
                    self._fail(ws, "bad request", err, 1003)
                    return
                try:
                    actions = _predict(policy, obs)
                except Exception as err:  # noqa: BLE001 - reported to the client, which raises PolicyError
                    log.exception("policy failed on a request")
                    self._fail(ws, "policy error", err, 1011)
                    return
                self.n_requests += 1
                timing = {"infer_ms": 1e3 * (time.perf_counter() - t0)}
                ws.send(packb({ACTIONS_KEY: actions, TIMING_KEY: timing}))
        except ConnectionClosed:
            return  # client left, or sent a message over max_message_bytes (closed with 1009)

    def _receive(self, ws):
        """The next message, or None once the client was idle for idle_timeout_s, or took longer than
        read_timeout_s to send a message it had begun (the connection is closed then)."""
        idle_end = None if self.idle_timeout_s is None else time.monotonic() + self.idle_timeout_s
        begun = None
        while True:
            try:
                return ws.recv(timeout=min(_POLL_S, self.read_timeout_s))
            except TimeoutError:
                now = time.monotonic()
            if _partial_message(ws):
                begun = begun or now
                if now - begun > self.read_timeout_s:
                    _fail_connection(ws, 1008, f"a message took over {self.read_timeout_s:g} s to arrive")
                    return None
            elif idle_end is not None and now >= idle_end:
                ws.close(1000, "idle time-out")
                return None

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


if __name__ == "__main__":  # the alias of `twinbench serve`
    from twinbench.cli import main

    raise SystemExit(main(["serve", *sys.argv[1:]]))
