"""A tiny study end to end (slow): the hidden real workcell, perception policies calibrated on it, real
rollouts and two stand-in twins through the runner and one store, metrics and the study page. The
reconstruction itself is tested in test_reconstruct; here the twins are the real workcell itself (a
perfect twin: its outcomes must equal the real ones) and the task's fast cell (a naive twin). Fast: the
command's checks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twinbench.cli import main as cli_main


def test_study_evaluate_needs_the_study_folder(tmp_path, capsys):
    assert cli_main(["study", "evaluate", str(tmp_path)]) == 2
    assert "needs real/world" in capsys.readouterr().err
    assert cli_main(["study", "run", "--out", str(tmp_path), "--size", "huge"]) == 2
    assert "study size 'huge' (--size)" in capsys.readouterr().err
    out = tmp_path / "study"
    assert cli_main(["study", "run", "--out", str(out), "--policy", "mine=expert", "--policy", "nope:x"]) == 2
    assert "policy spec 'nope:x': unknown policy kind 'nope'" in capsys.readouterr().err
    assert not out.exists()  # refused before any stage
    assert cli_main(["study", "run", "--out", str(out), "--device", "cuda:99"]) == 2  # a GPU it lacks
    assert "--device 'cuda:99'" in capsys.readouterr().err
    assert not out.exists()


@pytest.mark.slow
@pytest.mark.timeout(2400)  # 9 episodes of 90 steps (real workcell and two twins): > 10 min on 2 busy cores
def test_tiny_study_end_to_end(tmp_path, monkeypatch):
    from twinbench.evaluation.store import ResultsStore
    from twinbench.policies import spec as spec_module
    from twinbench.study import evaluate as E
    from twinbench.study.real import make_real
    from twinbench.study.report import write_study_report
    from twinbench.tasks import get_task
    from twinbench.twin.files import save_twin

    real = make_real("push-t", 0, tmp_path / "real", "small")
    cell = get_task("push-t").task_cls().default_twin("fast")
    save_twin(cell, tmp_path / "twins" / "cell")
    twins = {"perfect": real / "world", "cell": tmp_path / "twins" / "cell"}
    tiny = E.StudySize((0,), 3.0, 2)  # without real_again, which the call below asks for (--real-again)
    monkeypatch.setattr(spec_module, "POLICY_KINDS", dict(spec_module.POLICY_KINDS))  # evaluate adds perceive
    policies = E.make_policies("push-t", real / "world", tmp_path / "policies", tiny, None,
                               names=("p0-clean", "p5-noise4cm", "p7-noise8cm"))
    assert len(policies) == 3 and (tmp_path / "policies" / "calibration.json").is_file()
    E.run_evaluations("push-t", real / "world", twins, policies, tmp_path, tiny, workers=1,  # entry point
                      real_again=True)
    doc = E.write_study_json(tmp_path, "push-t", tiny, list(twins), {"evaluate": 1.0})
    assert json.loads((tmp_path / "study.json").read_text()) == doc

    store = ResultsStore(tmp_path / "results" / "results.sqlite")
    real_eps = store.episodes(E.REAL, domain="real")
    assert len(real_eps) == 3 and all(r.status == "ok" for r in real_eps)
    for row in doc["variants"]:  # the table's rates are the store's
        sim_eps = {(r.policy, r.init_state): r.success for r in store.episodes(E.twin_run_id(row["variant"]))}
        for d in row["policies"]:
            assert d["sim"] == float(sim_eps[(d["policy"], 0)]) and d["n_sim"] == d["n_real"] == 1
            assert d["real"] == float(next(r.success for r in real_eps if r.policy == d["policy"]))
    perfect = doc["variants"][0]
    assert perfect["mmrv"]["value"] == 0.0  # the same world and seeds: the same outcomes
    assert all(d["sim"] == d["real"] for d in perfect["policies"])
    assert perfect["replay"]["accuracy"] == 1.0 and perfect["replay"]["excluded"] == 0  # same world: exact
    assert np.isfinite(doc["variants"][1]["mmrv"]["value"])
    # the real workcell again with every episode seed offset: the same episodes otherwise, in the table
    again = store.episodes(E.REAL_AGAIN)
    assert sorted((r.policy, r.init_state, r.seed) for r in again) == sorted(
        (r.policy, r.init_state, r.seed + E.AGAIN_SEED) for r in real_eps)
    assert doc["real_again"]["n_episodes"] == {"sim": 3, "real": 3}

    page = write_study_report(tmp_path, doc, twins=twins).read_text()
    assert "real | perfect" in page and "real | cell" in page


def test_a_study_run_started_again_keeps_the_stages_it_finished(tmp_path, monkeypatch):
    """`study run` stopped in a stage and started again with the same arguments runs only from that stage
    (stand-in stages: the order and the record are what is tested); other arguments are refused; a
    finished stage whose files are gone runs again, and so do the stages after it. The policies stage and
    the real rollouts run on a thread beside the reconstruction (here it waits for them, so the order is
    fixed), and the evaluate stage runs every evaluation after it."""
    import threading

    from twinbench.errors import InputError
    from twinbench.study import evaluate as E
    from twinbench.study import evidence, real, reconstruct, report
    from twinbench.study.run import run_study

    calls: list[str] = []
    stop = {"reconstruct"}
    ahead = threading.Event()  # the real rollouts beside the reconstruction are done

    def stage(name, result):
        def fn(*args, **kwargs):
            if name == "reconstruct":
                assert ahead.wait(30)
                ahead.clear()
            if name == "evaluate" and kwargs.get("real_only"):
                calls.append("real-rollouts")
                ahead.set()
                return {}
            calls.append(name)
            if name in stop:
                stop.discard(name)
                raise KeyboardInterrupt
            out = result()
            for p in (out.values() if isinstance(out, dict) else [out]):
                if hasattr(p, "mkdir"):
                    p.mkdir(parents=True, exist_ok=True)
            return out
        return fn

    monkeypatch.setattr(real, "make_real", stage("make-real", lambda: tmp_path / "real"))
    monkeypatch.setattr(evidence, "make_evidence", stage("evidence", lambda: tmp_path / "evidence"))
    monkeypatch.setattr(reconstruct, "reconstruct",
                        stage("reconstruct", lambda: {"full": tmp_path / "twins" / "full"}))
    monkeypatch.setattr(E, "make_policies", stage("policies", lambda: ["p0=perceive:x.json"]))
    monkeypatch.setattr(E, "user_calibration", lambda ev: None)
    monkeypatch.setattr(E, "run_evaluations", stage("evaluate", lambda: {"real": 1.0}))
    monkeypatch.setattr(E, "training_records", lambda policies: [])
    monkeypatch.setattr(E, "write_study_json", lambda out, task, size, twins, seconds, extra: {
        "twins": twins, "seconds": dict(seconds), "policies": extra["policies"]})
    monkeypatch.setattr(report, "write_study_report", stage("report", lambda: tmp_path / "report.html"))

    out = tmp_path / "study"
    with pytest.raises(KeyboardInterrupt):
        run_study("push-t", out, "small", seed=3, log=lambda line: None)
    assert calls == ["make-real", "evidence", "policies", "real-rollouts", "reconstruct"]
    calls.clear()
    lines: list[str] = []
    doc = run_study("push-t", out, "small", seed=3, log=lines.append)
    # the reconstruction runs again, and with it the stages after it
    assert calls == ["policies", "real-rollouts", "reconstruct", "evaluate", "report"]
    assert "== make-real: finished earlier (" in lines[0] and "kept" in lines[0]
    assert doc["twins"] == ["full"] and doc["policies"] == ["p0=perceive:x.json"]
    assert set(doc["seconds"]) == {"make-real", "evidence", "reconstruct", "policies", "evaluate", "report"}
    with pytest.raises(InputError, match=r"holds a study run with other arguments \(seed: 3 there, 4 now\)"):
        run_study("push-t", out, "small", seed=4, log=lambda line: None)
    calls.clear()
    import shutil

    shutil.rmtree(tmp_path / "evidence")
    doc = run_study("push-t", out, "small", seed=3, log=lambda line: None)
    assert calls == ["evidence", "policies", "real-rollouts", "reconstruct", "evaluate", "report"]
    record = json.loads((out / "stages.json").read_text())
    assert sorted(record["done"]) == ["evidence", "make-real", "policies", "reconstruct"]
    assert record["done"]["reconstruct"]["result"] == {"full": str(tmp_path / "twins" / "full")}
    # the user's own policies join the evaluation, also in a run started again (not a stage argument)
    evaluated = []
    monkeypatch.setattr(E, "run_evaluations", lambda task, world, twins, policies, *a, **k: evaluated.append(
        policies) or {"real": 1.0})
    calls.clear()
    doc = run_study("push-t", out, "small", seed=3, log=lambda line: None, policies=["mine=expert@0.5"])
    assert calls == ["report"] and evaluated == [["p0=perceive:x.json", "mine=expert@0.5"]]
    with pytest.raises(InputError, match=r"policy spec 'nope:x': unknown policy kind 'nope'"):
        run_study("push-t", out, "small", seed=3, log=lambda line: None, policies=["nope:x"])
    with pytest.raises(InputError, match=r"'p0' is one of the study's own policies; name yours otherwise"):
        run_study("push-t", out, "small", seed=3, log=lambda line: None, policies=["p0=expert"])


@pytest.mark.timeout(300)
def test_ctrl_c_in_the_reconstruction_stops_the_real_rollouts_beside_it(tmp_path, monkeypatch):
    """A Ctrl-C reaches the main thread only: the real rollouts evaluated on the thread beside the
    reconstruction stop as an interrupted `eval` does (finished episodes kept, workers killed), so that
    `study run` exits at once instead of waiting for them to end (stand-in stages; the rollouts are a real
    evaluation in worker processes: point-reach, each episode >= 6 s)."""
    import multiprocessing as mp
    import threading
    import time

    from twinbench.evaluation.runner import evaluate
    from twinbench.evaluation.store import ResultsStore
    from twinbench.study import evaluate as E
    from twinbench.study import evidence, real, reconstruct
    from twinbench.study.run import run_study

    store = ResultsStore(tmp_path / "r.sqlite")
    jobs, interrupted = 8, []

    def rollouts(*args, real_only=False, **kwargs):
        assert real_only
        evaluate("point-reach", ["expert"], jobs, 2, "real-rollouts", store, output_dir=tmp_path,
                 env_kwargs={"step_delay_s": 0.5})

    def reconstruction(*args, **kwargs):  # interrupted once an episode beside it is in the store
        deadline = time.monotonic() + 120
        while not store.episodes("real-rollouts") and time.monotonic() < deadline:
            time.sleep(0.05)
        assert store.episodes("real-rollouts"), "no episode finished within 120 s"
        interrupted.append(time.monotonic())
        raise KeyboardInterrupt

    monkeypatch.setattr(real, "make_real", lambda *a, **k: tmp_path)
    monkeypatch.setattr(evidence, "make_evidence", lambda *a, **k: tmp_path)
    monkeypatch.setattr(E, "make_policies", lambda *a, **k: ["expert"])
    monkeypatch.setattr(E, "user_calibration", lambda ev: None)
    monkeypatch.setattr(E, "run_evaluations", rollouts)
    monkeypatch.setattr(reconstruct, "reconstruct", reconstruction)
    lines: list[str] = []
    with pytest.raises(KeyboardInterrupt):
        run_study("push-t", tmp_path / "study", "small", log=lines.append)
    assert time.monotonic() - interrupted[0] < 5  # the rollouts left would take >= 12 s
    kept = len(store.episodes("real-rollouts"))
    assert 0 < kept < jobs
    assert any(f"beside the reconstruction: interrupted: {kept} of {jobs} episodes of run 'real-rollouts'"
               in line for line in lines), lines
    assert not [t for t in threading.enumerate() if t.name == "twinbench-beside"]  # waited for
    assert not [p for p in mp.active_children() if p.name == "twinbench-worker"]  # killed, not left running


def test_user_policies_are_checked_before_a_study_runs():
    from twinbench.errors import InputError
    from twinbench.study.evaluate import with_user_policies

    study = ["p0-clean=perceive:a.json", "p1-noise1cm=perceive:b.json"]
    assert with_user_policies("push-t", study, ["mine=expert@0.3", "lerobot:ckpt/step_5?io=io.json"]) == [
        *study, "mine=expert@0.3", "lerobot:ckpt/step_5?io=io.json"]
    with pytest.raises(InputError, match=r"'p5-noise4cm' is one of the study's own policies; name yours "
                                         r"otherwise: --policy MINE=expert"):
        with_user_policies("push-t", None, ["p5-noise4cm=expert"])  # before the study's policies exist
    with pytest.raises(InputError, match=r"also 'expert@0.3''s; name it: --policy MINE=expert@0.3"):
        with_user_policies("push-t", study, ["expert@0.3", "expert@0.3"])
    with pytest.raises(InputError, match=r"policy name 'my policy'"):
        with_user_policies("push-t", study, ["my policy=expert"])


def test_a_moved_study_folder_keeps_its_stages_read_from_where_it_is_now(tmp_path):
    """A study folder moved (or copied) elsewhere: `study run` there keeps the finished stages and reads
    their twins and policies from the new folder, not the old one (gone, or a stale copy). Records from
    before the `root` field (the make-real stage's DIR/real tells their folder) too."""
    import shutil

    from twinbench.study.run import _Timer

    old = tmp_path / "a" / "study"
    for sub in ("real", "twins/full", "policies"):
        (old / sub).mkdir(parents=True)
    args = {"task": "push-t", "seed": 0}
    timer = _Timer(lambda line: None, old / "stages.json", args)
    timer("make-real", lambda: old / "real")
    timer("reconstruct", lambda: {"full": old / "twins" / "full"})
    timer("policies", lambda: [f"p0=perceive:{old}/policies/p0.json", "mine=expert@0.5"])
    legacy = json.loads((old / "stages.json").read_text())
    assert legacy.pop("root") == str(old)
    for where, doc in (("b", None), ("c", legacy)):
        new = tmp_path / where / "study"
        shutil.copytree(old, new)
        if doc is not None:  # a record written before the root field
            (new / "stages.json").write_text(json.dumps(doc))
        lines = []
        again = _Timer(lines.append, new / "stages.json", args)
        assert again("make-real", _never) == new / "real"
        assert again("reconstruct", _never) == {"full": new / "twins" / "full"}
        assert again("policies", _never) == [f"p0=perceive:{new}/policies/p0.json", "mine=expert@0.5"]
        assert all("kept" in line for line in lines)
    shutil.rmtree(old)  # the original gone: the copy still keeps its stages
    assert _Timer(lambda line: None, tmp_path / "b" / "study" / "stages.json", args)(
        "make-real", lambda: None) == tmp_path / "b" / "study" / "real"


def _never():
    raise AssertionError("a kept stage ran again")


@pytest.mark.timeout(300)
def test_sigterm_stops_a_study_run_and_what_it_started(tmp_path, processes):
    """SIGTERM (a scheduler's stop) to `twinbench study run` during the reconstruction takes Ctrl-C's path:
    the command it is running and the real rollouts beside it stop, it exits 143 saying how to resume, and
    no process it started is left."""
    import os
    import signal
    import subprocess
    import sys
    import time

    def cli_command_runs(pid: int) -> bool:  # one of the reconstruction's `twinbench ...` commands
        return any("twinbench.cli" in processes.cmdline(p) for p in processes.descendants(pid))

    def stages_done() -> set[str]:
        record = out / "stages.json"
        return set(json.loads(record.read_text())["done"]) if record.exists() else set()

    out = tmp_path / "study"
    proc = subprocess.Popen([sys.executable, "-m", "twinbench.cli", "study", "run", "--task", "push-t",
                             "--out", str(out), "--workers", "1"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    pids: list[int] = []
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None:  # the reconstruction's first command runs
            if "evidence" in stages_done() and cli_command_runs(proc.pid):
                break
            time.sleep(0.2)
        pids = processes.descendants(proc.pid)
        assert pids, "the study started no process within 240 s"
        proc.send_signal(signal.SIGTERM)
        text, _ = proc.communicate(timeout=60)
        assert proc.returncode == 143, text
        assert "twinbench study: terminated (SIGTERM); the same command started again keeps" in text
        assert "Traceback" not in text
        assert processes.wait_ended(pids, 5) == []
        assert "evidence" in stages_done()  # kept for the next run
    finally:
        if proc.poll() is None:
            proc.kill()
        for p in pids:
            if processes.alive(p):
                os.kill(p, signal.SIGKILL)
