"""`twinbench serve`: serve a local policy of a task over websocket (openpi's protocol).

`python -m twinbench.policies.server ...` is an alias of this command."""

from __future__ import annotations

import errno
import socket
import sys
from dataclasses import dataclass

from twinbench._runtime import quiet_warp
from twinbench.commands.env_options import parse_env_kwargs
from twinbench.errors import InputError
from twinbench.policies.protocol import API_KEY_ENV, DEFAULT_MAX_MESSAGE_BYTES, USES_ENVIRONMENT_STATE_KEY
from twinbench.policies.server import (
    DEFAULT_IDLE_TIMEOUT_S,
    DEFAULT_MAX_CONNECTIONS,
    DEFAULT_READ_TIMEOUT_S,
    PolicyServer,
)
from twinbench.policies.spec import make_policy, parse_policy_spec
from twinbench.tasks import get_task


@dataclass(frozen=True)
class ServeConfig:
    """Serve a local policy (spec string, e.g. expert or expert@0.3) of a task over websocket."""

    task: str = "point-reach"
    policy: str = "expert"
    host: str = "127.0.0.1"
    """interface to bind; 127.0.0.1 (loopback) keeps the server private to this machine"""
    port: int = 8000
    seed: int = 0
    max_message_bytes: int = DEFAULT_MAX_MESSAGE_BYTES
    max_connections: int = DEFAULT_MAX_CONNECTIONS
    idle_timeout_s: float = DEFAULT_IDLE_TIMEOUT_S
    read_timeout_s: float = DEFAULT_READ_TIMEOUT_S
    """a client that has begun a message but not sent all of it within this time is dropped"""
    env_kwargs: str = ""  # JSON object of env constructor arguments, as `twinbench eval --env-kwargs`


# (lowest, highest) of each numeric option: a connection holds a policy instance, a message its bytes
RANGES = {"port": (0, 65535), "max_connections": (1, 1024), "max_message_bytes": (1, 1 << 30),
          "idle_timeout_s": (1e-3, 7 * 86400.0), "read_timeout_s": (1e-3, 86400.0)}


def check_options(cfg: ServeConfig) -> None:
    """InputError naming the option for a value out of its range (`RANGES`) or a host that does not
    resolve."""
    for name, (lo, hi) in RANGES.items():
        value = getattr(cfg, name)
        if not lo <= value <= hi:  # NaN fails too
            raise InputError(f"--{name.replace('_', '-')} {value}: must be in [{lo}, {hi}]")
    try:
        socket.getaddrinfo(cfg.host, cfg.port, type=socket.SOCK_STREAM)
    except (OSError, UnicodeError) as err:
        raise InputError(f"--host {cfg.host!r}: not an address or a known host name ({err}); e.g. 127.0.0.1 "
                         "(this machine only) or 0.0.0.0 (every interface)") from None


def main(cfg: ServeConfig) -> int:
    check_options(cfg)
    task = get_task(cfg.task)
    spec = parse_policy_spec(cfg.policy)
    if spec.kind == "remote":
        raise ValueError("--policy: the server serves local policies (expert, expert@LEVEL, lerobot:PATH)")
    quiet_warp()  # the printed url is the first stdout line

    env = task.make_env(**parse_env_kwargs(cfg.env_kwargs))
    # A scripted expert acts from the environment_state it is sent (the metadata tells the client).
    uses_state = bool(getattr(make_policy(spec, task, env, seed=cfg.seed), "uses_environment_state", False))
    try:
        server = PolicyServer(lambda: make_policy(spec, task, env, seed=cfg.seed), host=cfg.host,
                              port=cfg.port, metadata={"task": cfg.task, "policy": cfg.policy,
                                                       USES_ENVIRONMENT_STATE_KEY: uses_state},
                              max_message_bytes=cfg.max_message_bytes, max_connections=cfg.max_connections,
                              idle_timeout_s=cfg.idle_timeout_s, read_timeout_s=cfg.read_timeout_s)
    except OSError as err:
        if err.errno not in (errno.EADDRINUSE, errno.EADDRNOTAVAIL, errno.EACCES):
            raise
        raise InputError(f"--host {cfg.host} --port {cfg.port}: cannot listen there ({err.strerror}); choose "
                         "another --port (0: any free one) or --host") from None
    key = f" (API key required, from {API_KEY_ENV})" if server.requires_api_key else ""
    if cfg.host not in ("127.0.0.1", "localhost", "::1") and not server.requires_api_key:
        print(f"warning: serving on {cfg.host} without an API key: anyone who can reach this port can use "
              f"the policy; set {API_KEY_ENV}", file=sys.stderr, flush=True)
    print(f"serving {cfg.policy} for {cfg.task}{key} on {server.url}", flush=True)
    try:
        server.serve_forever()
    except KeyboardInterrupt:
        server.close()
    return 0

