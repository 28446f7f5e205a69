"""`evaluate(..., worlds=N)` / `twinbench eval --worlds N`: episodes run as the worlds of one many-world env
give the records that one-at-a-time episodes give."""

from __future__ import annotations

import pytest

from twinbench.errors import InputError
from twinbench.evaluation.runner import evaluate
from twinbench.evaluation.store import ResultsStore

ENV = {"preset": "fast", "episode_seconds": 0.3, "settle_steps": 2}  # 9-step push-T episodes
FIELDS = ("policy", "checkpoint", "init_state", "seed", "success", "status", "steps")


def _key(rec) -> tuple:
    m = rec.metrics
    return tuple(getattr(rec, f) for f in FIELDS) + (m["sum_reward"], m["max_reward"], m.get("error"))


def test_worlds_give_the_records_of_single_episodes(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    policies = ["expert", "slow=expert@0.5"]
    episodes = "grid:0,5,10,15,3"  # 5 per policy: a full batch of 3 and a partial one of 2
    one = evaluate("push-t", policies, episodes, 0, "one", store, output_dir=tmp_path, env_kwargs=ENV)
    many = evaluate("push-t", policies, episodes, 0, "many", store, output_dir=tmp_path, env_kwargs=ENV,
                    worlds=3)
    assert [_key(r) for r in many] == [_key(r) for r in one]
    assert all(r.status == "ok" and r.steps == 9 for r in many)
    assert len({r.metrics["sum_reward"] for r in many}) > 3  # the episodes really differ
    # in a worker process too (the batch travels to it), and resumable: a second call runs nothing
    pooled = evaluate("push-t", policies, "grid:0,5,10", 1, "pooled", store, output_dir=tmp_path,
                      env_kwargs=ENV, worlds=2)
    assert [_key(r) for r in pooled] == [_key(r) for r in one if r.init_state in (0, 5, 10)]
    logs: list[str] = []
    evaluate("push-t", policies, "grid:0,5,10", 1, "pooled", store, output_dir=tmp_path, env_kwargs=ENV,
             worlds=2, log=logs.append)
    assert "0 to run" in logs[0]


def test_bad_world_counts_are_refused(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    for bad in (0, -2, 10_000):
        with pytest.raises(InputError, match="--worlds"):
            evaluate("push-t", ["expert"], 1, 0, "x", store, worlds=bad)
    with pytest.raises(InputError, match="--worlds 2: task 'point-reach'"):
        evaluate("point-reach", ["expert"], 1, 0, "x", store, worlds=2)


def test_worker_processes_share_the_cores(monkeypatch):
    """Each of N eval workers gets cores // N for its physics (a large twin splits its frames only when
    its worker has two cores), unless the user chose TWINBENCH_CPU_THREADS."""
    from twinbench import _runtime
    from twinbench._runtime import share_cores

    monkeypatch.delenv("TWINBENCH_CPU_THREADS", raising=False)
    monkeypatch.setattr(_runtime, "cpu_cores", lambda: 8)
    assert [share_cores(w) for w in (1, 2, 3, 8, 16)] == ["8", "4", "2", "1", "1"]
    monkeypatch.setenv("TWINBENCH_CPU_THREADS", "2")
    assert share_cores(8) == "2"
