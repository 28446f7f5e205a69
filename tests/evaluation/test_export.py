"""eval_info.json: LeRobot's eval_info shape with known aggregates."""

import json

import pytest

from twinbench.evaluation.export import eval_info, policy_folder, write_eval_infos
from twinbench.evaluation.store import EpisodeRecord


def rec(init_state, success, sum_r, max_r, wall, policy="act", ckpt="step_10", status="ok", video=None):
    return EpisodeRecord("r", "point-reach", policy, ckpt, 10, init_state, 100 + init_state, "sim", success,
                         status, 12, wall, video, {"sum_reward": sum_r, "max_reward": max_r})


def test_eval_info_known_values(tmp_path):
    recs = [rec(2, False, 1.0, 0.5, 2.0, status="sim_error"), rec(0, True, 3.0, 1.0, 1.0, video="v0.mp4"),
            rec(1, True, 5.0, 0.75, 3.0)]
    info = eval_info(recs)
    assert set(info) >= {"per_episode", "aggregated", "video_paths"}
    assert set(info["per_episode"][0]) >= {"episode_ix", "sum_reward", "max_reward", "success", "seed"}
    assert [e["init_state"] for e in info["per_episode"]] == [0, 1, 2]
    assert [e["episode_ix"] for e in info["per_episode"]] == [0, 1, 2]
    assert [e["seed"] for e in info["per_episode"]] == [100, 101, 102]
    agg = info["aggregated"]
    assert set(agg) == {"avg_sum_reward", "avg_max_reward", "pc_success", "eval_s", "eval_ep_s"}
    assert agg["avg_sum_reward"] == pytest.approx(3.0) and agg["avg_max_reward"] == pytest.approx(0.75)
    assert agg["pc_success"] == pytest.approx(200 / 3) and agg["eval_s"] == 6.0 and agg["eval_ep_s"] == 2.0
    assert info["video_paths"] == ["v0.mp4"] and info["per_episode"][2]["status"] == "sim_error"
    with pytest.raises(ValueError, match="one policy"):
        eval_info(recs + [rec(0, True, 1, 1, 1, policy="dp")])
    with pytest.raises(ValueError):
        eval_info([])
    paths = write_eval_infos(recs + [rec(0, True, 1.0, 1.0, 1.0, policy="dp", ckpt="")], tmp_path)
    assert [p.relative_to(tmp_path).as_posix() for p in paths] == ["act_step_10/eval_info.json",
                                                                     "dp/eval_info.json"]
    assert json.loads(paths[1].read_text())["aggregated"]["pc_success"] == 100.0
    assert policy_folder("my act", "a/b") == "my-act_a-b"
