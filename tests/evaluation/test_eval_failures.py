"""Failures shown (first reason on the console and in eval_info.json, exit 1 when all of a policy's
episodes failed), the policy time-out and warm-up before the first episode, no partial video left by an
interrupt, and eval_info.json in LeRobot 0.6's layout."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twinbench.cli import main as cli_main
from twinbench.evaluation.runner import EvaluationInterrupted, evaluate
from twinbench.evaluation.store import ResultsStore
from twinbench.tasks import register_task
from twinbench.tasks.point_reach import ENV_ID, PointReachExpert

CALLS: list = []


class Refuses:
    """A policy whose every call fails with a helpful reason."""

    def reset(self):
        pass

    def select_action(self, obs):
        raise RuntimeError("checkpoint expects 3 cameras, the env has 2")


class WarmRemote(PointReachExpert):
    """The point-reach expert with a remote policy's `timeout_s` and `warm_up(observation)`."""

    timeout_s = 30.0

    def __init__(self, fail_warm_up=False):
        super().__init__()
        self.fail_warm_up = fail_warm_up
        CALLS.append(("built", self))

    def warm_up(self, obs):
        CALLS.append(("warm_up", self.timeout_s, sorted(obs["pixels"])))
        if self.fail_warm_up:
            raise TimeoutError("no reply within 5.0 s (model still compiling?)")

    def select_action(self, obs):
        CALLS.append(("act", self.timeout_s))
        return super().select_action(obs)


class InterruptAtStep5(PointReachExpert):
    def reset(self):
        super().reset()
        self.t = 0

    def select_action(self, obs):
        self.t += 1
        if self.t == 5:
            raise KeyboardInterrupt
        return super().select_action(obs)


def _task(name, make):
    register_task(name, env_id=ENV_ID, make_expert=lambda env: make(), n_grid_states=8, description=name)


def test_a_policy_that_always_fails_shows_its_reason_and_exits_1(tmp_path, capsys):
    _task("refuses-test", Refuses)
    argv = ["eval", "--run-id", "f", "--task", "refuses-test", "--policy", "expert", "--policy", "ok=expert",
            "--episodes", "grid:0,3", "--workers", "0", "--db", str(tmp_path / "r.sqlite"), "--output-dir",
            str(tmp_path), "--no-progress"]
    assert cli_main(argv) == 1
    err = capsys.readouterr().err
    assert "expert: 0/2 successes (0.0%), 2 errors" in err
    assert ("first error (policy_error, init_state 0, seed 0): RuntimeError: checkpoint expects 3 cameras, "
            "the env has 2") in err
    assert "every episode of expert, ok ended in an error (exit status 1)" in err
    info = json.loads((tmp_path / "eval" / "f" / "expert" / "eval_info.json").read_text())
    assert info["errors"] == {"n_errors": 2, "n_episodes": 2, "first_error": {
        "status": "policy_error", "init_state": 0, "seed": 0,
        "reason": "RuntimeError: checkpoint expects 3 cameras, the env has 2"}}
    assert [e["error"] for e in info["per_episode"]] == ["RuntimeError: checkpoint expects 3 cameras, the "
                                                         "env has 2"] * 2
    # a policy with at least one clean episode exits 0 (its errors are still shown)
    assert cli_main(["eval", "--run-id", "g", "--task", "point-reach", "--policy", "expert", "--episodes",
                     "grid:0", "--workers", "0", "--db", str(tmp_path / "r.sqlite"), "--output-dir",
                     str(tmp_path), "--no-progress"]) == 0
    assert "first error" not in capsys.readouterr().err


def test_policy_timeout_and_warm_up_before_the_first_episode(tmp_path):
    _task("warm-test", WarmRemote)
    CALLS.clear()
    store = ResultsStore(tmp_path / "r.sqlite")
    recs = evaluate("warm-test", ["expert"], "grid:0,1,2", 0, "w", store, output_dir=tmp_path,
                    policy_timeout_s=5.0)
    assert [r.success for r in recs] == [True] * 3
    kinds = [c[0] for c in CALLS]
    assert kinds[:2] == ["built", "warm_up"] and kinds.count("warm_up") == 1 and kinds.count("built") == 1
    assert CALLS[1] == ("warm_up", 5.0, ["front", "wrist"])  # the time-out is set before the warm-up
    assert {c[1] for c in CALLS if c[0] == "act"} == {5.0}
    # without --policy-timeout the policy keeps its own
    CALLS.clear()
    evaluate("warm-test", ["expert"], "grid:0", 0, "w2", store, output_dir=tmp_path)
    assert CALLS[1] == ("warm_up", 30.0, ["front", "wrist"])
    with pytest.raises(ValueError, match="--policy-timeout -1"):
        evaluate("warm-test", ["expert"], "grid:0", 0, "w3", store, output_dir=tmp_path, policy_timeout_s=-1)
    # a failed warm-up is the policy's error, with its reason
    _task("cold-test", lambda: WarmRemote(fail_warm_up=True))
    cold = evaluate("cold-test", ["expert"], "grid:0", 0, "c", store, output_dir=tmp_path)
    assert cold[0].status == "policy_error"
    assert cold[0].metrics["error"] == ("warm-up request before the first episode: TimeoutError: no reply "
                                        "within 5.0 s (model still compiling?)")


def test_an_interrupted_episode_leaves_no_partial_video(tmp_path):
    _task("interrupt-test", InterruptAtStep5)
    store = ResultsStore(tmp_path / "r.sqlite")
    with pytest.raises(EvaluationInterrupted):
        evaluate("interrupt-test", ["expert"], "grid:0", 0, "i", store, output_dir=tmp_path, video=True)
    folder = tmp_path / "videos" / "i" / "expert"
    assert folder.is_dir() and list(folder.iterdir()) == []  # neither init0_seed0.mp4 nor its .partial.mp4
    # a partial file left by a run killed outright (SIGKILL) is removed when the run resumes
    stale = folder / "init0_seed0.partial.mp4"
    stale.write_bytes(b"\0" * 100)
    _task("interrupt-test", PointReachExpert)  # the same task, now without the interrupt: resume
    (rec,) = evaluate("interrupt-test", ["expert"], "grid:0", 0, "i", store, output_dir=tmp_path, video=True)
    assert sorted(p.name for p in folder.iterdir()) == ["init0_seed0.mp4"] == [rec.video_path.split("/")[-1]]


def test_eval_info_in_lerobot_0_6_layout(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    recs = evaluate("point-reach", ["expert@0.5"], "grid", 0, "l", store, output_dir=tmp_path)
    info = json.loads((tmp_path / "eval" / "l" / "expert_step_50000" / "eval_info.json").read_text())
    assert set(info) >= {"per_task", "per_group", "overall", "per_episode", "aggregated", "video_paths"}
    (task,) = info["per_task"]
    assert (task["task_group"], task["task_id"]) == ("point-reach", 0)
    assert set(task["metrics"]) == {"sum_rewards", "max_rewards", "successes", "video_paths",
                                    "predicted_video_paths"}
    assert task["metrics"]["successes"] == [r.success for r in sorted(recs, key=lambda r: r.init_state)]
    group = info["per_group"]["point-reach"]
    k = sum(r.success for r in recs)
    assert group["pc_success"] == pytest.approx(100 * k / 8) == info["overall"]["pc_success"]
    assert group["n_episodes"] == info["overall"]["n_episodes"] == 8
    mean_sum = np.mean([r.metrics["sum_reward"] for r in recs])
    assert info["overall"]["avg_sum_reward"] == pytest.approx(mean_sum)
    assert info["aggregated"]["pc_success"] == group["pc_success"]  # the older layout's keys agree
    assert all("final_metrics" in e and "distance" in e["final_metrics"] for e in info["per_episode"])
