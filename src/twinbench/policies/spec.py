"""Policy spec strings (CLI `--policy`) and policy kinds: a registry of kind -> how to parse and build it.

Grammar: `[NAME=]KIND[:TARGET][?OPTIONS]` (and `expert@LEVEL`). Built-in kinds:
- `expert`: the task's scripted expert (policy "expert", checkpoint "", train_step None);
- `expert@LEVEL`: `DegradedPolicy` of the expert at LEVEL in [0, 1] (checkpoint "step_<train_step>",
  train_step = round((1 - LEVEL) * 100000), see `twinbench.policies.degraded`);
- `remote:ws://HOST:PORT`: a websocket policy server (policy "remote", checkpoint "HOST": the port is
  where it runs today, not which policy it is; name served policies with `NAME=`);
- `lerobot:PATH`: a LeRobot `pretrained_model` folder (policy "lerobot"; checkpoint "step_N" and
  train_step N when PATH contains `checkpoints/<N>/`, else the folder name).
- `cnn:DIR`: a small CNN policy's checkpoint directory (`twinbench.policies.cnn`, the `torch` extra;
  policy "cnn", checkpoint the folder name); option `n_action_steps=N`.
- `actions:FILE.npy`: a recorded (T, A) array of actions played open loop, one row per step (policy
  "actions", checkpoint the file's stem), e.g. the files `eval --record-actions` writes; an episode
  that outlives its rows ends as a policy_error (`replay_episodes` stops it at T steps).
`NAME=` overrides the policy name stored with the episodes, e.g. `act=lerobot:outputs/.../pretrained_model`.
`KIND:TARGET` takes options after `?`: `io=PRESET_OR_JSON_FILE` (observation mapping and action
handling, `twinbench.policies.io`), `n_action_steps=N` and, for `remote:`, `timeout_s=SECONDS` (per
reply), e.g. `pi05=remote:ws://127.0.0.1:8000?io=openpi-libero&n_action_steps=5&timeout_s=60`.

Kinds from other packages: an entry point of group `twinbench.policies` whose name is the kind and whose
object is a factory with the built-in kinds' signature

    make(spec: PolicySpec, task: TaskSpec, env: gymnasium.Env, *, seed: int) -> Policy

(`spec.target`, `spec.io`, `spec.n_action_steps` carry the spec's TARGET and options; `seed` is the
episode's seed), or a `PolicyKind` (a factory plus its own spec parser). It is loaded the first time a
spec names a kind that is not registered; built-in kinds win over entry points of the same name. A
plugin kind's spec is `KIND` or `KIND:TARGET[?OPTIONS]`: policy name KIND (or NAME), checkpoint and
train_step from TARGET as for `lerobot:PATH` ("" without a target). In-process,
`register_policy_kind(name, make)` adds a kind; worker processes (`workers >= 1`) start fresh, so a kind
they must build comes from an entry point (or run with `workers=0`).
"""

from __future__ import annotations

import importlib.metadata
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from twinbench.errors import InputError
from twinbench.policies.degraded import DegradedPolicy, level_to_train_step

ENTRY_POINT_GROUP = "twinbench.policies"
_NAME_RE = re.compile(r"^[A-Za-z0-9_.\-]+$")
_KIND_RE = re.compile(r"^([A-Za-z][A-Za-z0-9_.\-]*)(.*)$", re.DOTALL)  # KIND, then ":TARGET" or "@LEVEL"
_FORMS = ("expert, expert@LEVEL, remote:ws://HOST:PORT, lerobot:PATH, cnn:DIR, actions:FILE.npy, "
          "KIND[:TARGET] of a plugin's kind (optionally prefixed NAME=)")


@dataclass(frozen=True)
class PolicySpec:
    """A parsed `--policy` string: what to build and the labels its episodes are stored under."""

    spec: str
    kind: str  # a registered kind: "expert" | "remote" | "lerobot" | a plugin's
    name: str
    checkpoint: str
    train_step: int | None
    level: float | None = None  # degradation level (expert@LEVEL)
    target: str = ""  # url (remote), path (lerobot), TARGET (a plugin's kind)
    io: str = ""  # policies.io preset name or JSON file ("" = the kind's default)
    n_action_steps: int | None = None
    timeout_s: float | None = None  # per reply (remote policies; None = the policy's default)


# (spec, NAME or None, the text after KIND: "", ":TARGET[?OPTIONS]" or "@LEVEL") -> PolicySpec
SpecParser = Callable[[str, str | None, str], PolicySpec]


@dataclass(frozen=True)
class PolicyKind:
    """A policy kind: `make(spec, task, env, *, seed) -> policy` and the parser of its spec strings
    (None: `KIND[:TARGET][?OPTIONS]`, labelled as the module docstring says)."""

    make: Callable[..., object]
    parse: SpecParser | None = None


POLICY_KINDS: dict[str, PolicyKind] = {}


def register_policy_kind(name: str, make: Callable[..., object], *, parse: SpecParser | None = None) -> None:
    """Add the policy kind `name` (specs `name`, `name:TARGET[?OPTIONS]`) built by `make`."""
    m = _KIND_RE.match(name)
    if not m or m.group(2):
        raise InputError(f"policy kind {name!r}: a kind is a letter then letters, digits, '_', '.', '-'")
    if name in POLICY_KINDS:
        raise InputError(f"policy kind {name!r} is already registered")
    POLICY_KINDS[name] = PolicyKind(make, parse)


def _entry_points() -> dict:
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def known_kinds() -> list[str]:
    """Registered kinds and the kinds installed packages offer (entry points, not loaded)."""
    return sorted(set(POLICY_KINDS) | set(_entry_points()))


def policy_kind(name: str, spec: str | None = None) -> PolicyKind:
    """The kind `name`: registered, else loaded from its `twinbench.policies` entry point; InputError
    listing the known kinds otherwise."""
    if name in POLICY_KINDS:
        return POLICY_KINDS[name]
    where = f"policy spec {spec!r}: " if spec is not None else ""
    ep = _entry_points().get(name)
    if ep is None:
        raise InputError(f"{where}unknown policy kind {name!r}; known kinds: {', '.join(known_kinds())} "
                         f"(more come from packages' {ENTRY_POINT_GROUP!r} entry points); "
                         f"accepted forms: {_FORMS}")
    try:
        obj = ep.load()
    except Exception as err:  # noqa: BLE001 - a broken plugin is named with its error
        raise InputError(f"{where}policy kind {name!r}: loading its entry point {ep.value!r} failed: "
                         f"{type(err).__name__}: {err}") from err
    if isinstance(obj, PolicyKind):
        POLICY_KINDS[name] = obj
    elif callable(obj):
        POLICY_KINDS[name] = PolicyKind(obj)
    else:
        raise InputError(f"{where}policy kind {name!r}: entry point {ep.value!r} is neither a factory "
                         f"(callable) nor a PolicyKind but a {type(obj).__name__}")
    return POLICY_KINDS[name]


def _split_options(spec: str, body: str) -> tuple[str, dict]:
    """`TARGET?io=X&n_action_steps=N&timeout_s=S` -> (TARGET, {"io": X, "n_action_steps": N, ...})."""
    target, sep, query = body.partition("?")
    if not sep:
        return body, {}
    opts: dict = {}
    for item in query.split("&"):
        key, eq, value = item.partition("=")
        if not eq or key not in ("io", "n_action_steps", "timeout_s") or not value:
            raise InputError(f"policy spec {spec!r}: options after '?' are io=PRESET_OR_FILE, "
                             f"n_action_steps=N and timeout_s=SECONDS, got {item!r}")
        if key == "timeout_s":
            try:
                value = float(value)
            except ValueError:
                value = -1.0
            if not value > 0:
                raise InputError(f"policy spec {spec!r}: timeout_s must be a number of seconds > 0")
        if key == "n_action_steps":
            if not value.isdigit() or int(value) < 1:
                raise InputError(f"policy spec {spec!r}: n_action_steps must be an integer >= 1")
            value = int(value)
        opts[key] = value
    return target, opts


def _path_labels(path: str) -> tuple[str, int | None]:
    """(checkpoint, train_step) of a checkpoint path: "step_N", N under `checkpoints/<N>/`, else the
    folder name ("" for no path)."""
    m = re.search(r"checkpoints/0*(\d+)(/|$)", Path(path).as_posix())
    if m:
        return f"step_{int(m.group(1))}", int(m.group(1))
    return (Path(path).name if path else ""), None


def parse_policy_spec(spec: str) -> PolicySpec:
    """Parse a policy spec string; InputError (a ValueError) naming the accepted forms otherwise."""
    if not isinstance(spec, str) or not spec.strip():
        raise InputError(f"policy spec must be a non-empty string; accepted forms: {_FORMS}")
    body, name = spec.strip(), None
    head, sep, rest = body.partition("=")
    if sep and ":" not in head and "@" not in head:
        if not _NAME_RE.match(head):
            raise InputError(f"policy name {head!r} in {spec!r} may only hold letters, digits, '_', '.', '-'")
        name, body = head, rest
    m = _KIND_RE.match(body)
    if not m or (m.group(2) and m.group(2)[0] not in ":@"):
        raise InputError(f"unknown policy spec {spec!r}; accepted forms: {_FORMS}")
    kind, rest = m.group(1), m.group(2)
    parse = policy_kind(kind, spec).parse or _parse_plugin(kind)
    return parse(spec, name, rest)


def _parse_plugin(kind: str) -> SpecParser:
    def parse(spec: str, name: str | None, rest: str) -> PolicySpec:
        if rest.startswith("@"):
            raise InputError(f"policy spec {spec!r}: expected {kind} or {kind}:TARGET[?OPTIONS]")
        target, opts = _split_options(spec, rest[1:])
        checkpoint, step = _path_labels(target)
        return PolicySpec(spec, kind, name or kind, checkpoint, step, None, target, **opts)

    return parse


def make_policy(spec: PolicySpec | str, task, env, *, seed: int = 0):
    """Build the policy described by `spec` for `task` (a TaskSpec) acting in `env`."""
    if isinstance(spec, str):
        spec = parse_policy_spec(spec)
    return policy_kind(spec.kind, spec.spec).make(spec, task, env, seed=seed)


# ---- built-in kinds ----------------------------------------------------------------------------------
def _parse_expert(spec: str, name: str | None, rest: str) -> PolicySpec:
    if not rest:
        return PolicySpec(spec, "expert", name or "expert", "", None, None)
    if not rest.startswith("@"):
        raise InputError(f"policy spec {spec!r}: expected expert or expert@LEVEL")
    try:
        level = float(rest[1:])
    except ValueError:
        raise InputError(f"policy spec {spec!r}: LEVEL in expert@LEVEL must be a number in [0, 1]") from None
    step = level_to_train_step(level)
    return PolicySpec(spec, "expert", name or "expert", f"step_{step}", step, level)


def _make_expert(spec: PolicySpec, task, env, *, seed: int):
    base = task.make_expert(env)
    if spec.level is None:
        return base
    return DegradedPolicy(base, spec.level, seed, env.action_space.low, env.action_space.high)


def _parse_remote(spec: str, name: str | None, rest: str) -> PolicySpec:
    url, opts = _split_options(spec, rest[1:]) if rest.startswith(":") else ("", {})
    m = re.match(r"^wss?://(\[[^]]+\]|[^/:]+)(:\d+)?(/|$)", url)
    if not m:
        raise InputError(f"policy spec {spec!r}: expected remote:ws://HOST:PORT")
    return PolicySpec(spec, "remote", name or "remote", m.group(1), None, None, url, **opts)


def _make_remote(spec: PolicySpec, task, env, *, seed: int):
    from twinbench.policies.io import load_policy_io
    from twinbench.policies.remote import RemotePolicy

    io = load_policy_io(spec.io).with_n_action_steps(spec.n_action_steps).bind(env)
    timeout = {} if spec.timeout_s is None else {"timeout_s": spec.timeout_s}
    policy = RemotePolicy(spec.target, prompt=getattr(env.unwrapped, "task_description", None),
                          n_action_steps=io.action.n_action_steps, **timeout)
    policy.io = io
    return policy


def _parse_lerobot(spec: str, name: str | None, rest: str) -> PolicySpec:
    path, opts = _split_options(spec, rest[1:]) if rest.startswith(":") else ("", {})
    if not path:
        raise InputError(f"policy spec {spec!r}: expected lerobot:PATH to a pretrained_model folder")
    checkpoint, step = _path_labels(path)
    return PolicySpec(spec, "lerobot", name or "lerobot", checkpoint, step, None, path, **opts)


def _make_lerobot(spec: PolicySpec, task, env, *, seed: int):
    from twinbench.policies.io import load_policy_io
    from twinbench.policies.lerobot_adapter import LeRobotPolicy

    description = getattr(env.unwrapped, "task_description", None) or ""
    io = load_policy_io(spec.io or None).bind(env)
    return LeRobotPolicy(spec.target, task_description=description, io=io, n_action_steps=spec.n_action_steps)


def _parse_cnn(spec: str, name: str | None, rest: str) -> PolicySpec:
    path, opts = _split_options(spec, rest[1:]) if rest.startswith(":") else ("", {})
    if not path or "io" in opts or "timeout_s" in opts:
        raise InputError(f"policy spec {spec!r}: expected cnn:DIR[?n_action_steps=N], DIR a checkpoint "
                         "directory of twinbench.policies.cnn")
    checkpoint, step = _path_labels(path)
    return PolicySpec(spec, "cnn", name or "cnn", checkpoint, step, None, path, **opts)


def _make_cnn(spec: PolicySpec, task, env, *, seed: int):
    from twinbench.policies.cnn import make_cnn

    return make_cnn(spec, task, env, seed=seed)


def _parse_actions(spec: str, name: str | None, rest: str) -> PolicySpec:
    path, opts = _split_options(spec, rest[1:]) if rest.startswith(":") else ("", {})
    if not path.endswith(".npy") or opts:
        raise InputError(f"policy spec {spec!r}: expected actions:FILE.npy (a (T, A) array of actions, "
                         "no options)")
    return PolicySpec(spec, "actions", name or "actions", Path(path).stem, None, None, path)


def _make_actions(spec: PolicySpec, task, env, *, seed: int):
    import numpy as np

    from twinbench.policies.base import OpenLoopPolicy

    try:
        actions = np.load(spec.target, allow_pickle=False)
    except (OSError, ValueError) as err:
        raise InputError(f"{spec.target}: cannot read the actions ({err}); give a .npy file of a "
                         "(T, A) numeric array") from None
    want = env.action_space.shape
    if actions.ndim != 2 or actions.shape[1:] != want or not np.issubdtype(actions.dtype, np.number):
        raise InputError(f"{spec.target}: actions of shape {actions.shape} ({actions.dtype}); task "
                         f"{task.name!r} needs a numeric (T, {', '.join(map(str, want))}) array")
    return OpenLoopPolicy(actions)


register_policy_kind("expert", _make_expert, parse=_parse_expert)
register_policy_kind("remote", _make_remote, parse=_parse_remote)
register_policy_kind("lerobot", _make_lerobot, parse=_parse_lerobot)
register_policy_kind("cnn", _make_cnn, parse=_parse_cnn)
register_policy_kind("actions", _make_actions, parse=_parse_actions)
