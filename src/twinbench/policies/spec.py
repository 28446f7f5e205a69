"""Policy spec strings (CLI `--policy`) and the factory that builds a policy from one.

Grammar: `[NAME=]SPEC` with SPEC one of
- `expert`: the task's scripted expert (policy "expert", checkpoint "", train_step None);
- `expert@LEVEL`: `DegradedPolicy` of the expert at LEVEL in [0, 1] (checkpoint "step_<train_step>",
  train_step = round((1 - LEVEL) * 100000), see `twinbench.policies.degraded`);
- `remote:ws://HOST:PORT`: a websocket policy server (policy "remote", checkpoint "HOST:PORT");
- `lerobot:PATH`: a LeRobot `pretrained_model` folder (policy "lerobot"; checkpoint "step_N" and
  train_step N when PATH contains `checkpoints/<N>/`, else the folder name).
`NAME=` overrides the policy name stored with the episodes, e.g. `act=lerobot:outputs/.../pretrained_model`.
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
        url = body[len("remote:"):]
        m = re.match(r"^wss?://([^/]+)", url)
        if not m:
            raise ValueError(f"policy spec {spec!r}: expected remote:ws://HOST:PORT")
        return PolicySpec(spec, "remote", name or "remote", m.group(1), None, None, url)
    if body.startswith("lerobot:"):
        path = body[len("lerobot:"):]
        if not path:
            raise ValueError(f"policy spec {spec!r}: expected lerobot:PATH to a pretrained_model folder")
        m = re.search(r"checkpoints/0*(\d+)(/|$)", Path(path).as_posix())
        step = int(m.group(1)) if m else None
        ckpt = f"step_{step}" if m else Path(path).name
        return PolicySpec(spec, "lerobot", name or "lerobot", ckpt, step, None, path)
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
        from twinbench.policies.remote import RemotePolicy

        return RemotePolicy(spec.target, prompt=description)
    if spec.kind == "lerobot":
        from twinbench.policies.lerobot_adapter import LeRobotPolicy

        return LeRobotPolicy(spec.target, task_description=description or "")
    raise ValueError(f"unknown policy kind {spec.kind!r}")
