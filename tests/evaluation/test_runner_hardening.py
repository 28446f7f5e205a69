"""Runner hardening (issue 14): crashed workers, parent death, SIGTERM, sizes, run ids, broken videos."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from twinbench.cli import main as cli_main
from twinbench.errors import InputError
from twinbench.evaluation import video as video_module
from twinbench.evaluation.rollout import run_episode
from twinbench.evaluation.runner import MAX_EPISODES, episode_set, evaluate
from twinbench.evaluation.store import ResultsStore
from twinbench.tasks import get_task
from twinbench.tasks.point_reach import PointReachExpert

ENV = {**os.environ, "PYTHONUNBUFFERED": "1"}


def _eval_cmd(tmp_path, run_id, *extra):
    return [sys.executable, "-m", "twinbench.cli", "eval", "--run-id", run_id, "--task", "point-reach",
            "--db", str(tmp_path / "r.sqlite"), "--output-dir", str(tmp_path), "--no-progress", *extra]


def _worker_pids(processes, parent: int, n: int, timeout_s: float = 30) -> list[int]:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        pids = [c for c in processes.children(parent) if "spawn_main" in processes.cmdline(c)]
        if len(pids) >= n:
            return pids
        time.sleep(0.05)
    raise AssertionError(f"no {n} worker processes under {parent}")


def test_worker_dying_in_an_episode_is_a_sim_error_and_the_run_goes_on(tmp_path):
    # fail_step 13: the expert finishes every grid episode in 12 steps; expert@1.0 wanders on and its
    # worker process dies (os._exit, as a segfault would) at step 13 of each of its episodes.
    store = ResultsStore(tmp_path / "r.sqlite")
    kwargs = {"fail_mode": "exit", "fail_step": 13}
    recs = evaluate("point-reach", ["expert", "expert@1.0"], "grid:0,1,2", 2, "crash", store,
                    output_dir=tmp_path, env_kwargs=kwargs)
    by = {(r.checkpoint, r.init_state): r for r in recs}
    expert = [(by["", i].status, by["", i].success, by["", i].steps) for i in range(3)]
    assert expert == [("ok", True, 12)] * 3
    for i in range(3):
        r = by["step_0", i]
        assert (r.status, r.success) == ("sim_error", False)
        assert r.metrics["error"] == "worker process died during the episode (exit code 70)"
    assert len(store.episodes("crash")) == 6
    # re-running (even retrying the errors) records them again instead of aborting
    again = evaluate("point-reach", ["expert", "expert@1.0"], "grid:0,1,2", 1, "crash", store,
                     output_dir=tmp_path, env_kwargs=kwargs, retry_errors=True)
    assert [r.status for r in again] == ["ok"] * 3 + ["sim_error"] * 3


def test_a_script_without_a_main_guard_is_told_so_instead_of_running_again_in_its_workers(tmp_path):
    # spawn's workers import the parent's script: unguarded, every worker would run the whole script
    # (another evaluation, a study's stages) into the same files
    script = tmp_path / "unguarded.py"
    script.write_text(
        "from twinbench.evaluation.runner import evaluate\n"
        f"evaluate('point-reach', ['expert'], 2, 2, 'g', {str(tmp_path / 'r.sqlite')!r}, "
        f"output_dir={str(tmp_path)!r})\n"
        "print('the parent finished')\n")
    proc = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, env=ENV,
                          timeout=120, cwd=tmp_path)
    assert proc.returncode == 1 and "the parent finished" not in proc.stdout
    assert "InputError: evaluate was called while a worker process imports your script" in proc.stderr
    assert 'RuntimeError: a worker process exited (exit code 1) before it started' in proc.stderr
    assert ResultsStore(tmp_path / "r.sqlite").episodes("g") == []  # nothing recorded as the episodes' fault
    guarded = tmp_path / "guarded.py"
    guarded.write_text("if __name__ == '__main__':\n" + "".join(
        "    " + line + "\n" for line in script.read_text().splitlines()))
    proc = subprocess.run([sys.executable, str(guarded)], capture_output=True, text=True, env=ENV,
                          timeout=120, cwd=tmp_path)
    assert proc.returncode == 0 and "the parent finished" in proc.stdout, proc.stderr
    assert [e.status for e in ResultsStore(tmp_path / "r.sqlite").episodes("g")] == ["ok", "ok"]


def test_a_bad_env_kwarg_is_one_input_error_not_a_crash(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    with pytest.raises(InputError, match=r"--env-kwargs .*no_such_option"):
        evaluate("point-reach", ["expert"], 2, 2, "kw", store, output_dir=tmp_path,
                 env_kwargs={"no_such_option": 1})


def test_parent_sigkill_takes_the_workers_with_it(tmp_path, processes):
    # each episode takes >= 12 s (12 steps of 1 s): the workers are inside one when the parent dies
    proc = subprocess.Popen(_eval_cmd(tmp_path, "kill", "--policy", "expert", "--episodes", "8", "--workers",
                                      "2", "--env-kwargs", '{"step_delay_s": 1.0}'),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=ENV)
    try:
        workers = _worker_pids(processes, proc.pid, 2)
        # kill a second after an episode is stored: both workers are then past their start-up (a busy
        # machine can take longer than any fixed sleep to import) and inside their next episodes, which
        # run >= 11 s more, so within the 3 s below only their watch on the parent can end them
        store, deadline = ResultsStore(tmp_path / "r.sqlite"), time.monotonic() + 120
        while not store.episodes("kill") and time.monotonic() < deadline:
            time.sleep(0.2)
        assert store.episodes("kill"), "no episode finished within 120 s"
        time.sleep(1.0)
        proc.kill()
        proc.wait(timeout=10)
        assert processes.wait_ended(workers, 3) == []
    finally:
        for p in workers if "workers" in locals() else []:
            if processes.alive(p):
                os.kill(p, signal.SIGKILL)


def test_sigterm_is_handled_like_ctrl_c(tmp_path, processes):
    proc = subprocess.Popen(_eval_cmd(tmp_path, "term", "--policy", "expert", "--episodes", "8", "--workers",
                                      "2", "--env-kwargs", '{"step_delay_s": 0.03}'),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=ENV)
    store = ResultsStore(tmp_path / "r.sqlite")
    workers = _worker_pids(processes, proc.pid, 2)
    deadline = time.monotonic() + 60
    while len(store.episodes("term")) < 2 and time.monotonic() < deadline:
        time.sleep(0.05)
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=30)
    kept = len(store.episodes("term"))
    assert proc.returncode == 143, out
    assert 2 <= kept < 8
    assert f"terminated (SIGTERM): {kept} of 8 episodes of run 'term'" in out and "Traceback" not in out
    assert not any(processes.alive(p) for p in workers)


def test_huge_episode_count_is_refused_up_front(tmp_path, capsys):
    t0 = time.monotonic()
    with pytest.raises(InputError, match="at most"):
        episode_set(8, 1_000_000_000, 0)
    assert len(episode_set(8, MAX_EPISODES, 0)) == MAX_EPISODES
    assert cli_main(["eval", "--run-id", "big", "--task", "point-reach", "--policy", "expert", "--episodes",
                     "1000000000", "--db", str(tmp_path / "r.sqlite"), "--output-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--episodes 1000000000" in err[0] and time.monotonic() - t0 < 10


@pytest.mark.parametrize("run_id", ["../../x", "/tmp/abs", "a/b", "..", ".hidden", "", "x" * 129])
def test_run_ids_are_names_not_paths(tmp_path, run_id):
    out = tmp_path / "out"
    with pytest.raises(InputError, match="run id"):
        evaluate("point-reach", ["expert"], 1, 0, run_id, tmp_path / "r.sqlite", output_dir=out)
    assert not out.exists() and not Path("/tmp/abs").exists()
    assert ResultsStore(tmp_path / "r.sqlite").runs() == []


def test_a_video_cut_short_by_a_full_disk_is_reported_missing(tmp_path):
    # RLIMIT_FSIZE makes ffmpeg's writes fail with EFBIG past 1500 bytes (the complete file is ~2 kB),
    # exactly as a full disk does; the episode itself must be unaffected.
    video = tmp_path / "v.mp4"
    code = f"""
import json, resource, warnings
from twinbench.evaluation.rollout import run_episode
from twinbench.tasks import get_task
from twinbench.tasks.point_reach import PointReachExpert
resource.setrlimit(resource.RLIMIT_FSIZE, (1500, 1500))
with warnings.catch_warnings(record=True) as w:
    warnings.simplefilter("always")
    out = run_episode(get_task("point-reach").make_env(), PointReachExpert(), init_state=0, seed=0,
                      video_path={str(video)!r})
print(json.dumps({{"status": out.status, "success": out.success, "video": out.video_path,
                  "error": out.video_error, "warned": [str(x.message) for x in w]}}))
"""
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert (out["status"], out["success"], out["video"]) == ("ok", True, None)
    assert str(video) in out["error"] and any("video missing" in m for m in out["warned"])
    assert not video.exists()
    # the same episode without the limit writes a complete MP4
    ok = run_episode(get_task("point-reach").make_env(), PointReachExpert(), init_state=0, seed=0,
                     video_path=video)
    assert ok.video_path == str(video) and ok.video_error is None and video_module.mp4_complete(video)
    size = video.stat().st_size
    with video.open("r+b") as fh:
        fh.truncate(size - 100)
    assert not video_module.mp4_complete(video)


def test_eval_warns_and_records_a_missing_video(tmp_path, monkeypatch):
    monkeypatch.setattr(video_module, "mp4_complete", lambda path: False)  # every file looks truncated
    logs = []
    with pytest.warns(UserWarning, match="video missing"):
        recs = evaluate("point-reach", ["expert"], "grid:0,1", 0, "vid", tmp_path / "r.sqlite", video=True,
                        output_dir=tmp_path, log=logs.append)
    assert [(r.status, r.success, r.video_path) for r in recs] == [("ok", True, None)] * 2
    assert all("truncated" in r.metrics["video_error"] for r in recs)
    assert sum("warning: video missing for expert init_state" in m for m in logs) == 2
    info = json.loads((tmp_path / "eval" / "vid" / "expert" / "eval_info.json").read_text())
    assert info["video_paths"] == []


def test_worker_and_seed_bounds_and_safe_policy_folders(tmp_path):
    from twinbench.evaluation.export import policy_folder

    for workers, seed in ((100_000, 0), (-1, 0), (1, -5), (1, 2**63)):
        with pytest.raises(InputError, match="--workers|--seed"):
            evaluate("point-reach", ["expert"], 1, workers, "w", tmp_path / "r.sqlite", seed=seed,
                     output_dir=tmp_path)
    assert policy_folder("..", "") == "_." and policy_folder(".", "") == "_"
    assert policy_folder("a/../..", "x") == "a-..-.._x" and "/" not in policy_folder("/etc", "passwd")
    recs = evaluate("point-reach", ["..=expert"], 1, 0, "dots", tmp_path / "r.sqlite", output_dir=tmp_path)
    assert recs[0].policy == ".." and (tmp_path / "eval" / "dots" / "_." / "eval_info.json").is_file()


def test_progress_lines_for_logs_print_at_most_once_a_minute_with_an_eta():
    from twinbench.progress import ProgressLines

    now, out = [100.0], []
    lines = ProgressLines(out.append, "eval r", total=10, done=2, clock=lambda: now[0])
    for t, done in ((30.0, 3), (61.0, 4), (90.0, 5), (125.0, 6)):
        now[0] = 100.0 + t
        lines.update(done, lambda done=done: f"{done} successes")
    # 2 of 8 to do finished in 61 s: 6 left at 30.5 s each; then 4 in 125 s: 4 left at 31.25 s each
    assert out == ["eval r: 4/10 (4 successes), elapsed 0:01:01, ETA 0:03:03",
                   "eval r: 6/10 (6 successes), elapsed 0:02:05, ETA 0:02:05"]
    now[0] += 1.0
    lines.update(10)  # the end of a run that printed: always a last line
    assert out[-1] == "eval r: 10/10, elapsed 0:02:06, ETA 0:00:00"
    quiet = []
    short = ProgressLines(quiet.append, "eval s", total=3, clock=lambda: 0.0)
    short.update(3)  # a run shorter than a minute prints nothing
    assert quiet == []


@pytest.mark.parametrize("workers", [0, 1])
def test_a_run_beside_the_main_thread_stops_on_its_event(tmp_path, workers):
    """No signal reaches a thread other than the main one: a run under `stop_requests` stops as after
    Ctrl-C once its event is set (in this process between batches; with workers, while they are busy),
    the finished episodes kept."""
    import threading

    from twinbench.evaluation.backends import stop_requests
    from twinbench.evaluation.runner import EvaluationInterrupted

    store = ResultsStore(tmp_path / "r.sqlite")
    event, out = threading.Event(), {}

    def run():
        with stop_requests(event):
            try:
                evaluate("point-reach", ["expert"], 6, workers, "beside", store, output_dir=tmp_path,
                         env_kwargs={"step_delay_s": 0.1})
            except EvaluationInterrupted as err:
                out["err"] = err

    thread = threading.Thread(target=run)
    thread.start()
    deadline = time.monotonic() + 120
    while not store.episodes("beside") and time.monotonic() < deadline:
        time.sleep(0.02)
    event.set()
    thread.join(timeout=30)
    assert not thread.is_alive()
    kept = len(store.episodes("beside"))
    assert 0 < kept < 6 and out["err"].done == kept and out["err"].total == 6
