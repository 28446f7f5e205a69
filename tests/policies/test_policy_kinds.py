"""Policy kinds as a registry: a kind from another package's `twinbench.policies` entry point (a real
dist-info on sys.path, also seen by worker processes), in-process registration, unknown kinds."""

from __future__ import annotations

import importlib.metadata
import textwrap

import pytest

from twinbench.errors import InputError
from twinbench.policies import make_policy, parse_policy_spec, register_policy_kind
from twinbench.policies import spec as spec_module
from twinbench.tasks import get_task

PLUGIN = '''
import numpy as np


class GoTo:
    """point-reach: always commands the absolute target (x, y)."""

    def __init__(self, xy):
        self.xy = np.asarray(xy, dtype=np.float32)

    def reset(self):
        pass

    def select_action(self, obs):
        return self.xy


def make(spec, task, env, *, seed):
    return GoTo([float(v) for v in spec.target.split(",")])
'''


@pytest.fixture
def kinds(monkeypatch):
    """A private copy of the registry, so kinds registered or loaded here vanish after the test; without the
    kinds that an earlier test in this process loaded from entry points (the study's `perceive`), so that
    what a test sees does not depend on which tests ran before it."""
    offered = spec_module._entry_points()
    own = {k: v for k, v in spec_module.POLICY_KINDS.items() if k not in offered}
    monkeypatch.setattr(spec_module, "POLICY_KINDS", own)
    return spec_module.POLICY_KINDS


@pytest.fixture
def plugin(tmp_path, monkeypatch, kinds):
    """An installed distribution (dist-info on sys.path) offering policy kind "goto"."""
    (tmp_path / "goto_plugin.py").write_text(textwrap.dedent(PLUGIN))
    info = tmp_path / "goto_plugin-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: goto-plugin\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text("[twinbench.policies]\ngoto = goto_plugin:make\n")
    monkeypatch.syspath_prepend(str(tmp_path))  # spawned worker processes are given this sys.path
    return tmp_path


def test_a_kind_from_an_entry_point_is_loaded_when_a_spec_names_it(plugin, kinds):
    assert "goto" in spec_module.known_kinds() and "goto" not in kinds  # offered, not loaded yet
    s = parse_policy_spec("home=goto:0,0?n_action_steps=2")
    assert (s.kind, s.name, s.checkpoint, s.train_step, s.target, s.n_action_steps) == (
        "goto", "home", "0,0", None, "0,0", 2)
    assert "goto" in kinds
    s = parse_policy_spec("goto:runs/checkpoints/0300/model")  # checkpoint labels as for lerobot:PATH
    assert (s.name, s.checkpoint, s.train_step) == ("goto", "step_300", 300)
    with pytest.raises(InputError, match="expected goto or goto:TARGET"):
        parse_policy_spec("goto@0.5")
    task = get_task("point-reach")
    policy = make_policy("goto:0.1,-0.05", task, task.make_env())
    assert policy.xy.tolist() == pytest.approx([0.1, -0.05])


def test_a_plugin_kind_runs_in_worker_processes(plugin, tmp_path):
    from twinbench.evaluation.runner import evaluate

    # known answers: targeting the goal (0, 0) reaches and holds it; a far corner never does
    recs = evaluate("point-reach", ["goto:0,0", "goto:0.25,0.25"], "grid:0,3", 1, "plug",
                    tmp_path / "r.sqlite", output_dir=tmp_path)
    assert [(r.policy, r.checkpoint, r.init_state, r.status, r.success) for r in recs] == [
        ("goto", "0,0", 0, "ok", True), ("goto", "0,0", 3, "ok", True),
        ("goto", "0.25,0.25", 0, "ok", False), ("goto", "0.25,0.25", 3, "ok", False)]


def test_unknown_kind_lists_the_known_ones(monkeypatch, kinds):
    class FakeEntryPoint:
        name, value = "broken", "no_such_module:make"

        def load(self):
            raise ModuleNotFoundError("No module named 'no_such_module'")

    def entry_points(*, group):
        return [FakeEntryPoint()] if group == "twinbench.policies" else []

    monkeypatch.setattr(importlib.metadata, "entry_points", entry_points)
    with pytest.raises(InputError, match=r"unknown policy kind 'nope'; known kinds: actions, broken, cnn, "
                                         r"expert, lerobot, remote"):
        parse_policy_spec("nope:x")
    with pytest.raises(InputError, match=r"'broken'.*'no_such_module:make' failed: ModuleNotFoundError"):
        parse_policy_spec("broken:x")


def test_register_policy_kind_in_process(kinds):
    register_policy_kind("const", lambda spec, task, env, *, seed: ("const", spec.target, seed))
    task = get_task("point-reach")
    assert make_policy("const:abc", task, task.make_env(), seed=7) == ("const", "abc", 7)
    with pytest.raises(InputError, match="already registered"):
        register_policy_kind("expert", lambda spec, task, env, *, seed: None)
    with pytest.raises(InputError, match="a kind is a letter"):
        register_policy_kind("two:parts", lambda spec, task, env, *, seed: None)


def test_actions_kind_plays_a_recorded_npy_and_names_bad_files(tmp_path):
    import numpy as np

    from twinbench.errors import PolicyError

    task = get_task("point-reach")
    env = task.make_env()
    acts = np.array([[0.1, -0.2], [0.0, 0.05]], np.float32)
    np.save(tmp_path / "ep3.npy", acts)
    spec = parse_policy_spec(f"actions:{tmp_path / 'ep3.npy'}")
    assert (spec.kind, spec.name, spec.checkpoint, spec.train_step) == ("actions", "actions", "ep3", None)
    policy = make_policy(spec, task, env, seed=0)
    policy.reset()
    np.testing.assert_array_equal([policy.select_action({}), policy.select_action({})], acts)
    with pytest.raises(PolicyError, match="exhausted after 2 steps"):
        policy.select_action({})
    for bad in ("actions", "actions:x.json", f"actions:{tmp_path / 'ep3.npy'}?io=x"):
        with pytest.raises(InputError, match="actions:FILE.npy"):
            parse_policy_spec(bad)
    np.save(tmp_path / "wide.npy", np.zeros((4, 3)))
    with pytest.raises(InputError, match=r"wide.npy: actions of shape \(4, 3\).*needs a numeric \(T, 2\)"):
        make_policy(parse_policy_spec(f"actions:{tmp_path / 'wide.npy'}"), task, env, seed=0)
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(InputError, match="obj.npy: cannot read the actions"):  # never unpickled
        make_policy(parse_policy_spec(f"actions:{tmp_path / 'obj.npy'}"), task, env, seed=0)
    with pytest.raises(InputError, match="missing.npy: cannot read"):
        make_policy(parse_policy_spec(f"actions:{tmp_path / 'missing.npy'}"), task, env, seed=0)
