"""Evaluation runner: parallel runs, resume, error statuses, videos, and SIGINT + resume via the CLI."""

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest

from twinbench.evaluation.runner import episode_set, evaluate
from twinbench.evaluation.store import ResultsStore
from twinbench.tasks import register_task
from twinbench.tasks.point_reach import ENV_ID


def test_two_workers_grid_and_resume(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    logs = []
    recs = evaluate("point-reach", ["expert", "expert@1.0"], "grid", 2, "run1", store, output_dir=tmp_path,
                    log=logs.append)
    assert len(recs) == 16 and len(store.episodes("run1")) == 16
    expert = [r for r in recs if r.checkpoint == ""]
    assert [r.init_state for r in expert] == list(range(8)) and [r.seed for r in expert] == list(range(8))
    assert all(r.success and r.status == "ok" and r.steps == 12 for r in expert)  # analytic: 12 steps
    # rewards 1 - d / 0.25 with d = 0.16, 0.14, ..., 0.02 over steps 1-8, then 0: 8 - 0.72 / 0.25 + 4
    for r in expert:
        assert set(r.metrics) == {"sum_reward", "max_reward", "started_at", "final"}  # no "error" on success
        assert r.metrics["final"] == {"distance": pytest.approx(0.0, abs=1e-9)}  # the last frame's metrics
        assert (r.metrics["sum_reward"], r.metrics["max_reward"]) == pytest.approx((9.12, 1.0))
    bad = [r for r in recs if r.checkpoint == "step_0"]
    assert all(r.train_step == 0 and r.status == "ok" for r in bad) and sum(r.success for r in bad) < 8
    info = json.loads((tmp_path / "eval" / "run1" / "expert" / "eval_info.json").read_text())
    assert info["aggregated"]["pc_success"] == 100.0 and len(info["per_episode"]) == 8
    spent = store.run_seconds("run1")
    assert spent > 0 and store.run_seconds("never") is None
    # same run again: nothing re-run, the very same records come back (and no time is added)
    recs2 = evaluate("point-reach", ["expert", "expert@1.0"], "grid", 2, "run1", store, output_dir=tmp_path,
                     log=logs.append)
    assert "16 already finished, 0 to run" in logs[-1] and store.run_seconds("run1") == spent
    assert [r.metrics["started_at"] for r in recs2] == [r.metrics["started_at"] for r in recs]
    # the same run with fewer policies runs nothing new; with more, it is extended by their episodes only
    assert evaluate("point-reach", ["expert"], "grid", 0, "run1", store, output_dir=tmp_path) == expert
    logs.clear()
    more = evaluate("point-reach", ["expert", "expert@1.0", "expert@0.5"], "grid", 0, "run1", store,
                    output_dir=tmp_path, log=logs.append)
    assert "adding 1 policies" in logs[0] and "24 episodes, 16 already finished, 8 to run" in logs[1]
    assert more[:16] == recs and len(store.episodes("run1")) == 24  # job order: the policies' order
    assert store.run_seconds("run1") > spent  # the extension's time adds to the run's
    assert store.run_protocol("run1")["policies"] == ["expert", "expert@1.0", "expert@0.5"]
    # any other difference of protocol under the same run id is refused (here the episodes)
    keys = r"\['episodes', 'init_states', 'policies', 'seeds'\]"
    with pytest.raises(ValueError, match=f"different protocol keys {keys}"):
        evaluate("point-reach", ["expert"], "grid:0,1", 0, "run1", store, output_dir=tmp_path)


def test_sampled_episodes_determinism_and_partial_resume(tmp_path):
    assert episode_set(8, 3, 10) == [(8, 10), (9, 11), (10, 12)]
    assert episode_set(8, "grid:0,5,7", 10) == [(0, 10), (5, 15), (7, 17)]
    for bad in ("grid:0,8", "grid:1,1", "grid:a"):
        with pytest.raises(ValueError, match="grid"):
            episode_set(8, bad, 0)
    with pytest.raises(ValueError, match="episodes"):
        episode_set(8, "all", 0)
    store = ResultsStore(tmp_path / "r.sqlite")
    a = evaluate("point-reach", ["expert@0.5"], 6, 0, "a", store, output_dir=tmp_path)
    b = evaluate("point-reach", ["expert@0.5"], 6, 2, "b", store, output_dir=tmp_path)  # other workers
    assert [(r.success, r.steps) for r in a] == [(r.success, r.steps) for r in b]  # same seeds, same episodes
    # resume: a run that already holds 2 of its episodes only runs the other 4
    for r in a[:2]:
        store.record_episode(type(r)(**{**r.__dict__, "run_id": "c"}))
    store.start_run("c", "point-reach", store.run_protocol("a"))
    logs = []
    c = evaluate("point-reach", ["expert@0.5"], 6, 0, "c", store, output_dir=tmp_path, log=logs.append)
    assert "2 already finished, 4 to run" in logs[0]
    assert [(r.success, r.steps) for r in c] == [(r.success, r.steps) for r in a]


class CrashAtStep3:
    def __init__(self):
        self.t = 0

    def reset(self):
        self.t = 0

    def select_action(self, obs):
        self.t += 1
        if self.t == 3:
            raise RuntimeError("model exploded")
        return np.zeros(2, np.float32)


def test_error_statuses(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    nan = evaluate("point-reach", ["expert"], 2, 0, "nan", store,
                   env_kwargs={"fail_mode": "nan", "fail_step": 4}, output_dir=tmp_path)
    assert [(r.status, r.success, r.steps) for r in nan] == [("sim_error", False, 4)] * 2
    assert all("at step 4: point_reach: position [nan nan] is not finite" in r.metrics["error"] for r in nan)
    raised = evaluate("point-reach", ["expert"], 1, 0, "raise", store,
                      env_kwargs={"fail_mode": "raise", "fail_step": 2}, output_dir=tmp_path)
    assert raised[0].status == "sim_error" and "SimulationDiverged" in raised[0].metrics["error"]
    register_task("crash-test", env_id=ENV_ID, make_expert=lambda env: CrashAtStep3(), n_grid_states=8,
                  description="point-reach with a crashing expert")
    crash = evaluate("crash-test", ["expert"], 1, 0, "crash", store, output_dir=tmp_path)
    assert (crash[0].status, crash[0].steps) == ("policy_error", 2)
    assert "model exploded" in crash[0].metrics["error"]
    with pytest.raises(ValueError, match="known tasks"):
        evaluate("nope", ["expert"], 1, 0, "x", store)
    with pytest.raises(ValueError, match="duplicate"):
        evaluate("point-reach", ["expert", "expert"], 1, 0, "x", store)


def test_videos(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    recs = evaluate("point-reach", ["expert"], "grid", 0, "vid", store, video=True, output_dir=tmp_path)
    path = Path(recs[0].video_path)
    assert path == tmp_path / "videos" / "vid" / "expert" / "init0_seed0.mp4"
    frames = iio.imread(path)
    assert frames.shape == (13, 64, 128, 3)  # reset frame + 12 steps; both cameras side by side by default
    info = json.loads((tmp_path / "eval" / "vid" / "expert" / "eval_info.json").read_text())
    assert len(info["video_paths"]) == 8
    assert not list(tmp_path.rglob("*.partial.mp4"))  # complete videos are renamed from their temporary name
    logs = []
    front = evaluate("point-reach", ["expert"], "grid:0", 0, "vid1", store, video=True, output_dir=tmp_path,
                     video_views="front", log=logs.append)
    assert iio.imread(front[0].video_path).shape == (13, 64, 64, 3)
    assert any("videos: cameras front" in m for m in logs)
    both = iio.imread(path)[0].astype(int)
    # the left half of the side-by-side video is the front camera's frame (lossy codec: close, not equal)
    assert np.abs(both[:, :64] - iio.imread(front[0].video_path)[0].astype(int)).mean() < 4
    with pytest.raises(ValueError, match="unknown camera.*top.*front"):
        evaluate("point-reach", ["expert"], "grid:0", 0, "vid2", store, video=True, output_dir=tmp_path,
                 video_views="top")


def test_sigint_then_resume_via_cli(tmp_path):
    db = tmp_path / "r.sqlite"
    cmd = [sys.executable, "-m", "twinbench.cli", "eval", "--run-id", "sig", "--task", "point-reach",
           "--policy", "expert", "--policy", "expert@0.6", "--episodes", "6", "--workers", "2",
           "--db", str(db), "--output-dir", str(tmp_path), "--env-kwargs", '{"step_delay_s": 0.03}',
           "--no-progress"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    # SIGINT at its default in the child even when this suite runs with it ignored (a background job)
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    store = ResultsStore(db)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        if os.path.exists(db) and len(store.episodes("sig")) >= 3:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    out, _ = proc.communicate(timeout=30)
    first = {(r.policy, r.checkpoint, r.init_state, r.seed): r.metrics["started_at"]
             for r in store.episodes("sig")}
    assert proc.returncode == 130, out
    assert 3 <= len(first) < 12
    assert f"interrupted: {len(first)} of 12 episodes" in out and "re-run the same command" in out
    out2 = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=120)
    assert out2.returncode == 0, out2.stdout + out2.stderr
    assert f"{len(first)} already finished, {12 - len(first)} to run" in out2.stderr
    final = store.episodes("sig")
    assert len(final) == 12  # every episode exactly once (unique key in the store)
    for r in final:  # episodes finished before SIGINT were not redone
        k = (r.policy, r.checkpoint, r.init_state, r.seed)
        if k in first:
            assert r.metrics["started_at"] == first[k]


def test_ray_backend_matches_local(tmp_path):
    """Needs the 'ray' extra (skipped without it; CI installs it): starts a local Ray instance."""
    ray = pytest.importorskip("ray")
    store = ResultsStore(tmp_path / "r.sqlite")
    try:
        on_ray = evaluate("point-reach", ["expert", "expert@0.5"], "grid", 2, "ray", store, backend="ray",
                          output_dir=tmp_path)
    finally:
        ray.shutdown()
    local = evaluate("point-reach", ["expert", "expert@0.5"], "grid", 0, "local", store, output_dir=tmp_path)
    assert len(on_ray) == 16 and len(store.episodes("ray")) == 16
    def key(recs):
        return [(r.policy, r.checkpoint, r.init_state, r.seed, r.success, r.steps, r.status) for r in recs]

    assert key(on_ray) == key(local)


def test_parse_env_kwargs():
    from twinbench.commands.env_options import parse_env_kwargs

    assert parse_env_kwargs("") == {}
    assert parse_env_kwargs('{"step_delay_s": 0.01, "fail_mode": null}') == {"step_delay_s": 0.01,
                                                                             "fail_mode": None}
    with pytest.raises(ValueError, match="JSON object"):
        parse_env_kwargs("{step_delay_s: 1}")
    with pytest.raises(ValueError, match=r"JSON object \(dict\)"):
        parse_env_kwargs("[1, 2]")
