"""Open-loop replay from LeRobotDataset-v3-shaped folders, JSON and NPZ logs; confusion matrices."""

import json
from dataclasses import replace

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from twinbench.evaluation.replay import (
    RecordedEpisode,
    confusion_counts,
    load_recorded,
    replay_confusion,
    replay_episodes,
)
from twinbench.evaluation.store import ResultsStore

GOOD = np.zeros((14, 2), np.float32)  # go to the goal: the twin succeeds (12 steps)
BAD = np.full((14, 2), 0.2, np.float32)  # go to a corner: the twin fails

# (init_state, actions, real success, checkpoint) -> replay/real: TP, FN, FP, TN, TP
EPISODES = [(0, GOOD, True, "step_1"), (1, BAD, True, "step_1"), (2, GOOD, False, "step_1"),
            (3, BAD, False, "step_2"), (4, GOOD, True, "step_2")]


def write_lerobot_v3(root, with_outcomes=True):
    (root / "meta" / "episodes" / "chunk-000").mkdir(parents=True)
    (root / "data" / "chunk-000").mkdir(parents=True)
    info = {"codebase_version": "v3.0", "fps": 10, "total_episodes": len(EPISODES),
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "features": {"action": {"dtype": "float32", "shape": [2], "names": None},
                         "observation.state": {"dtype": "float32", "shape": [2], "names": None}}}
    (root / "meta" / "info.json").write_text(json.dumps(info))
    rows = {"action": [], "observation.state": [], "episode_index": [], "frame_index": [], "index": []}
    for ep, (_, acts, _, _) in enumerate(EPISODES):
        for t in reversed(range(len(acts))):  # stored out of order: the reader must sort by frame_index
            rows["action"].append(acts[t].tolist())
            rows["observation.state"].append([0.0, 0.0])
            rows["episode_index"].append(ep)
            rows["frame_index"].append(t)
            rows["index"].append(len(rows["index"]))
    # split the frames over two data files, as large datasets are
    table = pa.table(rows)
    pq.write_table(table.slice(0, 30), root / "data" / "chunk-000" / "file-000.parquet")
    pq.write_table(table.slice(30), root / "data" / "chunk-000" / "file-001.parquet")
    meta = {"episode_index": list(range(len(EPISODES))), "length": [len(e[1]) for e in EPISODES],
            "tasks": [["reach"]] * len(EPISODES)}
    if with_outcomes:
        meta |= {"init_state": [e[0] for e in EPISODES], "success": [e[2] for e in EPISODES],
                 "policy": ["act"] * len(EPISODES), "checkpoint": [e[3] for e in EPISODES]}
    pq.write_table(pa.table(meta), root / "meta" / "episodes" / "chunk-000" / "file-000.parquet")


def check(store, run_id):
    by_ckpt = replay_confusion(store, run_id)
    c1, c2 = by_ckpt[("point-reach", "act", "step_1")], by_ckpt[("point-reach", "act", "step_2")]
    assert (c1.tp, c1.fp, c1.fn, c1.tn) == (1, 1, 1, 0) and (c2.tp, c2.fp, c2.fn, c2.tn) == (1, 0, 0, 1)
    total = replay_confusion(store, run_id, by="task")[("point-reach",)]
    assert (total.tp, total.fp, total.fn, total.tn, total.n) == (2, 1, 1, 1, 5)
    assert total.accuracy == pytest.approx(0.6)
    real = store.episodes(run_id, domain="real")
    expected = [(e[0], i, e[2]) for i, e in enumerate(EPISODES)]  # seed = recorded episode index
    assert [(r.init_state, r.seed, r.success) for r in real] == expected


def test_replay_lerobot_v3_folder(tmp_path):
    write_lerobot_v3(tmp_path / "ds")
    eps = load_recorded(tmp_path / "ds")
    assert [e.init_state for e in eps] == [0, 1, 2, 3, 4]
    np.testing.assert_array_equal(eps[1].actions, BAD)
    store = ResultsStore(tmp_path / "r.sqlite")
    pairs = replay_episodes("point-reach", eps, store, "rp")
    spent = store.run_seconds("rp")
    assert spent > 0  # the run's wall time (kept across sessions): a resumed replay with none left adds none
    assert replay_episodes("point-reach", eps, store, "rp") == pairs and store.run_seconds("rp") == spent
    assert [(real.success, rep.success) for real, rep in pairs] == [
        (True, True), (True, False), (False, True), (False, False), (True, True)]
    assert pairs[0][1].steps == 12 and pairs[1][1].steps == 14  # success terminates; else actions run out
    # rewards 1 - d / 0.25 with d = 0.16, 0.14, ..., 0.02, then 0 for steps 9-12: 8 - 0.72 / 0.25 + 4
    final = pairs[0][1].metrics.pop("final")
    assert final == {"distance": pytest.approx(0.0, abs=1e-9)}  # the last frame's task metrics are kept
    assert pairs[0][1].metrics == pytest.approx({"episode_index": 0, "sum_reward": 9.12, "max_reward": 1.0})
    check(store, "rp")
    # a replay that ended in an error is counted in `excluded`, never as a replay failure
    real, rep = pairs[0]
    store.record_episodes([replace(real, seed=99), replace(rep, seed=99, success=False, status="sim_error")])
    c1 = replay_confusion(store, "rp")[("point-reach", "act", "step_1")]
    assert (c1.tp, c1.fp, c1.fn, c1.tn, c1.excluded) == (1, 1, 1, 0, 1)
    assert replay_confusion(store, "rp")[("point-reach", "act", "step_2")].excluded == 0


def test_outcomes_file_and_validation(tmp_path):
    write_lerobot_v3(tmp_path / "ds", with_outcomes=False)
    with pytest.raises(ValueError, match="init_state"):
        load_recorded(tmp_path / "ds")
    outcomes = [{"episode_index": i, "init_state": e[0], "success": e[2], "policy": "act", "checkpoint": e[3]}
                for i, e in enumerate(EPISODES)]
    (tmp_path / "out.json").write_text(json.dumps({"episodes": outcomes}))
    eps = load_recorded(tmp_path / "ds", tmp_path / "out.json")
    assert [e.success for e in eps] == [e[2] for e in EPISODES]
    info = tmp_path / "ds" / "meta" / "info.json"
    info.write_text(json.dumps({"codebase_version": "v2.1", "features": {"action": {}}}))
    with pytest.raises(ValueError, match="v3"):
        load_recorded(tmp_path / "ds")
    with pytest.raises(ValueError, match="does not exist"):
        load_recorded(tmp_path / "nope.json")


def test_replay_json_and_npz_logs(tmp_path):
    log = {"episodes": [{"init_state": e[0], "actions": e[1].tolist(), "success": e[2], "policy": "act",
                         "checkpoint": e[3]} for e in EPISODES]}
    (tmp_path / "log.json").write_text(json.dumps(log))
    store = ResultsStore(tmp_path / "r.sqlite")
    replay_episodes("point-reach", load_recorded(tmp_path / "log.json"), store, "rj")
    check(store, "rj")
    np.savez(tmp_path / "log.npz", init_state=[e[0] for e in EPISODES], success=[e[2] for e in EPISODES],
             policy=["act"] * 5, checkpoint=[e[3] for e in EPISODES], lengths=[len(e[1]) for e in EPISODES],
             actions=np.concatenate([e[1] for e in EPISODES]))
    replay_episodes("point-reach", load_recorded(tmp_path / "log.npz"), store, "rn")
    check(store, "rn")
    bad = {"episodes": [{"init_state": 0, "actions": [[0, 0, 0]], "success": True, "policy": "a",
                         "checkpoint": ""}]}
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="expects"):
        replay_episodes("point-reach", load_recorded(tmp_path / "bad.json"), store, "rb")
    (tmp_path / "bad2.json").write_text(json.dumps({"episodes": [{"init_state": 0, "actions": [[0, 0]]}]}))
    with pytest.raises(ValueError, match="success"):
        load_recorded(tmp_path / "bad2.json")


def test_confusion_counts():
    c = confusion_counts([(True, True), (True, False), (False, True), (False, False), (False, False)])
    assert (c.tp, c.fp, c.fn, c.tn, c.n) == (1, 1, 1, 2, 5)
    assert c.accuracy == pytest.approx(3 / 5) and c.excluded == 0
    assert np.isnan(confusion_counts([]).accuracy)


def test_replay_cli(tmp_path, capsys):
    from twinbench.cli import main

    write_lerobot_v3(tmp_path / "ds")
    db = tmp_path / "r.sqlite"
    assert main(["replay", "--source", str(tmp_path / "ds"), "--db", str(db), "--run-id", "cli"]) == 0
    out = capsys.readouterr().out
    assert "act / step_1: TP=1 FP=1 FN=1 TN=0" in out and "point-reach: TP=2 FP=1 FN=1 TN=1" in out
    check(ResultsStore(db), "cli")


def test_replay_from_measured_poses_robot_logs_and_an_index_map(tmp_path):
    """A push-T recording as the reference study keeps it: its own indices (mapped here), the block's
    measured start pose, and flange poses per frame instead of actions."""
    from twinbench.tasks import get_task

    env = get_task("push-t").make_env(preset="fast")
    pose = [0.45, 0.05, 0.3]
    _, info = env.reset(seed=0, options={"init_state": 0, "object_poses": {"block": pose}})
    assert info["privileged"]["environment_state"][:3] == pytest.approx(pose, abs=2e-3)  # after settling
    with pytest.raises(ValueError, match="object_poses.*'lid'.*give a role"):
        env.reset(options={"object_poses": {"lid": pose}})
    flange = np.tile([0.30, -0.20, 0.10, 1.0, 0.0, 0.0, 0.0], (3, 1))
    flange[:, 0] += [0.0, 0.01, 0.02]
    log = {"episodes": [{"init_state": 7, "ee_poses": flange.tolist(), "success": False, "policy": "dp",
                         "checkpoint": "", "object_poses": {"tblock": pose}}]}
    (tmp_path / "log.json").write_text(json.dumps(log))
    (tmp_path / "map.json").write_text(json.dumps({"7": 2}))
    store = ResultsStore(tmp_path / "r.sqlite")
    (real, rep), = replay_episodes("push-t", load_recorded(tmp_path / "log.json"), store, "rp",
                                   env_kwargs={"preset": "fast"}, index_map=tmp_path / "map.json")
    assert (real.init_state, rep.init_state, rep.metrics["study_index"]) == (2, 2, 7)
    assert rep.status == "ok" and rep.steps == 3 and rep.metrics["object_poses"] == {"tblock": pose}
    assert set(rep.metrics["final"]) >= {"msd", "coverage"}
    assert store.run_protocol("rp")["grid"]["n_states"] == 16
    bad = {"episodes": [{**log["episodes"][0], "ee_poses": [[0.3, 0.1, 0.1]]}]}
    (tmp_path / "bad.json").write_text(json.dumps(bad))
    with pytest.raises(ValueError, match="'ee_poses' must be \\(T, 7\\)"):
        load_recorded(tmp_path / "bad.json")


def test_recorded_actions_replayed_in_the_same_world_give_the_same_outcomes(tmp_path):
    """`evaluate(record_actions=True)` writes each episode's commanded actions; replayed open loop in the
    same world they reproduce every outcome and step count."""
    from twinbench.evaluation.runner import actions_file, evaluate

    store = ResultsStore(tmp_path / "r.sqlite")
    recs = evaluate("point-reach", ["expert", "poor=expert@0.95"], "grid:0,1,2", workers=0, run_id="rec",
                    store=store, output_dir=tmp_path, record_actions=True)
    assert len(recs) == 6 and {r.success for r in recs} == {True, False}  # both outcomes present
    episodes = []
    for i, r in enumerate(recs):
        acts = np.load(actions_file(tmp_path, "rec", r.policy, r.checkpoint, r.init_state, r.seed))
        assert acts.shape == (r.steps, 2) and np.all(np.isfinite(acts))
        episodes.append(RecordedEpisode(i, r.init_state, acts, r.success, r.policy, r.checkpoint,
                                        seed=r.seed))
    pairs = replay_episodes("point-reach", episodes, store, "rep")
    assert [(rep.success, rep.steps) for _, rep in pairs] == [(r.success, r.steps) for r in recs]
    assert not list(tmp_path.rglob("*.partial"))


def test_replay_in_worker_processes_matches_in_process_and_resumes(tmp_path):
    """`workers=2` replays each episode in a worker (its actions as an `actions:FILE.npy` policy) with the
    outcomes, steps and rewards of the in-process replay; run again, a replay run replays only the
    episodes it does not hold with status ok."""
    eps = [RecordedEpisode(i, s, a, ok, "act", c) for i, (s, a, ok, c) in enumerate(EPISODES)]
    store = ResultsStore(tmp_path / "r.sqlite")
    here = replay_episodes("point-reach", eps, store, "in")
    first = replay_episodes("point-reach", eps, store, "pool")
    store.record_episodes([replace(rep, success=False, status="sim_error") for _, rep in first[2:]])
    pooled = replay_episodes("point-reach", eps, store, "pool", workers=2)

    def outcome(rep):
        return rep.success, rep.status, rep.steps, rep.metrics["sum_reward"], rep.metrics["episode_index"]

    assert [outcome(rep) for _, rep in pooled] == [outcome(rep) for _, rep in here]
    assert [r.wall_time_s for _, r in pooled[:2]] == [r.wall_time_s for _, r in first[:2]]  # not run again
    assert all("started_at" in r.metrics for _, r in pooled[2:])  # ran in a worker
    check(store, "pool")


def test_a_replay_run_grows_with_more_recorded_episodes(tmp_path):
    """A study that gains policies replays their real rollouts into the existing run: only the new episodes
    are replayed, the protocol's count follows; another twin under the same run id is still refused."""
    eps = [RecordedEpisode(i, s, a, ok, "act", c) for i, (s, a, ok, c) in enumerate(EPISODES)]
    store = ResultsStore(tmp_path / "r.sqlite")
    first = replay_episodes("point-reach", eps[:2], store, "grow")
    both = replay_episodes("point-reach", eps, store, "grow")
    assert [r.wall_time_s for _, r in both[:2]] == [r.wall_time_s for _, r in first]  # not run again
    assert len(store.episodes("grow", domain="replay")) == len(eps)
    assert store.run_protocol("grow")["n_episodes"] == len(eps)
    with pytest.raises(ValueError, match="different protocol keys"):
        replay_episodes("point-reach", eps, store, "grow", env_kwargs={"fail_step": 7})


def test_a_pyarrow_that_fails_to_import_is_named_with_the_fix(tmp_path, monkeypatch):
    """pyarrow >= 26 imports only with numpy >= 2, which its metadata does not say: beside numpy 1.x (openpi)
    a user gets pyarrow 26 and an ImportError; the message says which pyarrow to install."""
    import sys

    from twinbench.evaluation.replay import _read_parquet

    monkeypatch.setitem(sys.modules, "pyarrow", None)  # `import pyarrow` raises ImportError
    with pytest.raises(ImportError, match=r"x\.parquet needs pyarrow.*pyarrow>=18,<26"):
        _read_parquet(tmp_path / "x.parquet")
