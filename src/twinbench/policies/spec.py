"""Policy spec strings (CLI `--policy`) and the factory that builds a policy from one.

Grammar: `[NAME=]SPEC` with SPEC one of
- `expert`: the task's scripted expert (policy "expert", checkpoint "", train_step None);
- `expert@LEVEL`: `DegradedPolicy` of the expert at LEVEL in [0, 1] (checkpoint "step_<train_step>",
  train_step = round((1 - LEVEL) * 100000), see `twinbench.policies.degraded`);
- `remote:ws://HOST:PORT`: a websocket policy server (policy "remote", checkpoint "HOST": the port is
  where it runs today, not which policy it is; name served policies with `NAME=`);
- `lerobot:PATH`: a LeRobot `pretrained_model` folder (policy "lerobot"; checkpoint "step_N" and
  train_step N when PATH contains `checkpoints/<N>/`, else the folder name).
`NAME=` overrides the policy name stored with the episodes, e.g. `act=lerobot:outputs/.../pretrained_model`.
`remote:` and `lerobot:` take options after `?`: `io=PRESET_OR_JSON_FILE` (observation mapping and action
handling, `twinbench.policies.io`) and `n_action_steps=N`, e.g.
`pi05=remote:ws://127.0.0.1:8000?io=openpi-libero&n_action_steps=5`.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from twinbench.policies.degraded import DegradedPolicy, level_to_train_step

_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")


@dataclass(frozen=True)
class PolicySpec:
    """A parsed `--policy` string: what to build and the labels its episodes are stored under."""

    spec: str
    kind: str  # "expert" | "remote" | "lerobot"
    name: str
    checkpoint: str
    train_step: int | None
    level: float | None = None  # degradation level (expert@LEVEL)
    target: str = ""  # url (remote) or path (lerobot)
    io: str = ""  # policies.io preset name or JSON file ("" = the kind's default)
    n_action_steps: int | None = None


def _split_options(spec: str, body: str) -> tuple[str, dict]:
    """`TARGET?io=X&n_action_steps=N` -> (TARGET, {"io": X, "n_action_steps": N})."""
    target, sep, query = body.partition("?")
    if not sep:
        return body, {}
    opts: dict = {}
    for item in query.split("&"):
        key, eq, value = item.partition("=")
        if not eq or key not in ("io", "n_action_steps") or not value:
            raise ValueError(f"policy spec {spec!r}: options after '?' are io=PRESET_OR_FILE and "
                             f"n_action_steps=N, got {item!r}")
        if key == "n_action_steps":
            if not value.isdigit() or int(value) < 1:
                raise ValueError(f"policy spec {spec!r}: n_action_steps must be an integer >= 1")
            value = int(value)
        opts[key] = value
    return target, opts


def parse_policy_spec(spec: str) -> PolicySpec:
    """Parse a policy spec string; ValueError naming the accepted forms otherwise."""
    forms = "expert, expert@LEVEL, remote:ws://HOST:PORT, lerobot:PATH (optionally prefixed NAME=)"
    if not isinstance(spec, str) or not spec.strip():
        raise ValueError(f"policy spec must be a non-empty string; accepted forms: {forms}")
    body, name = spec.strip(), None
    head, sep, rest = body.partition("=")
    if sep and ":" not in head and "@" not in head:
        if not _NAME_RE.match(head):
            raise ValueError(f"policy name {head!r} in {spec!r} may only hold letters, digits, '_', '.', '-'")
        name, body = head, rest
    if body == "expert":
        return PolicySpec(spec, "expert", name or "expert", "", None, None)
    if body.startswith("expert@"):
        try:
            level = float(body[len("expert@"):])
        except ValueError:
            raise ValueError(f"policy spec {spec!r}: LEVEL in expert@LEVEL must be a number "
                             "in [0, 1]") from None
        step = level_to_train_step(level)
        return PolicySpec(spec, "expert", name or "expert", f"step_{step}", step, level)
    if body.startswith("remote:"):
        url, opts = _split_options(spec, body[len("remote:"):])
        m = re.match(r"^wss?://(\[[^]]+\]|[^/:]+)(:\d+)?(/|$)", url)
        if not m:
            raise ValueError(f"policy spec {spec!r}: expected remote:ws://HOST:PORT")
        return PolicySpec(spec, "remote", name or "remote", m.group(1), None, None, url, **opts)
    if body.startswith("lerobot:"):
        path, opts = _split_options(spec, body[len("lerobot:"):])
        if not path:
            raise ValueError(f"policy spec {spec!r}: expected lerobot:PATH to a pretrained_model folder")
        m = re.search(r"checkpoints/0*(\d+)(/|$)", Path(path).as_posix())
        step = int(m.group(1)) if m else None
        ckpt = f"step_{step}" if m else Path(path).name
        return PolicySpec(spec, "lerobot", name or "lerobot", ckpt, step, None, path, **opts)
    raise ValueError(f"unknown policy spec {spec!r}; accepted forms: {forms}")


def make_policy(spec: PolicySpec | str, task, env, *, seed: int = 0):
    """Build the policy described by `spec` for `task` (a TaskSpec) acting in `env`."""
    if isinstance(spec, str):
        spec = parse_policy_spec(spec)
    description = getattr(env.unwrapped, "task_description", None)
    if spec.kind == "expert":
        base = task.make_expert(env)
        if spec.level is None:
            return base
        return DegradedPolicy(base, spec.level, seed, env.action_space.low, env.action_space.high)
    if spec.kind == "remote":
        from twinbench.policies.io import load_policy_io
        from twinbench.policies.remote import RemotePolicy

        io = load_policy_io(spec.io).with_n_action_steps(spec.n_action_steps)
        policy = RemotePolicy(spec.target, prompt=description, n_action_steps=io.action.n_action_steps)
        policy.io = io
        return policy
    if spec.kind == "lerobot":
        from twinbench.policies.lerobot_adapter import LeRobotPolicy

        return LeRobotPolicy(spec.target, task_description=description or "", io=spec.io or None,
                             n_action_steps=spec.n_action_steps)
    raise ValueError(f"unknown policy kind {spec.kind!r}")
