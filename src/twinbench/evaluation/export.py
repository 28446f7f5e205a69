"""`eval_info.json` in the layout LeRobot 0.6's eval script (`lerobot_eval.py`, `eval_policy_all`) writes,
with the older layout's keys kept beside it.

LeRobot 0.6 keys: `per_task` = [{"task_group", "task_id", "metrics": {"sum_rewards", "max_rewards",
"successes", "video_paths", "predicted_video_paths"}}] (one entry: task_group = the twinbench task,
task_id 0), `per_group` = {task: {"avg_sum_reward", "avg_max_reward", "pc_success" (percent),
"n_episodes", "video_paths", "predicted_video_paths"}} and `overall` = the same plus "eval_s" and
"eval_ep_s" (nan-means, as LeRobot's `np.nanmean`).

Kept from the older layout (LeRobot < 0.4 `eval_policy`, and readers written for it, e.g. scripts that
read `aggregated.pc_success`): `per_episode` = [{"episode_ix", "sum_reward", "max_reward", "success",
"seed"}], `aggregated` and `video_paths`.

Differences, by necessity: episodes come from parallel workers and possibly several resumed sessions, so
`eval_s` is the sum of the episodes' own wall times (not one wall-clock span) and
`eval_ep_s = eval_s / n_episodes`; episodes are ordered by (init_state, seed); an episode that ended in an
error counts as a failure (its status and error are in the extra per-episode `status` / `error` fields;
the results store keeps it separate). Extra fields: `policy`, `checkpoint`, `train_step`, `task`,
per-episode `init_state`, `status`, `error` and `final_metrics` (the task's metrics at the last frame),
and `errors` = {"n_errors", "n_episodes", "first_error" (status, init_state, seed, reason) or null}.
"""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

from twinbench.evaluation.store import EpisodeRecord


def _nanmean(values: list[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else float("nan")


def first_error(records: list[EpisodeRecord]) -> dict | None:
    """The first failed episode (by init_state, seed) of `records`: status, init_state, seed and reason."""
    for r in sorted(records, key=lambda r: (r.init_state, r.seed)):
        if r.status != "ok":
            return {"status": r.status, "init_state": int(r.init_state), "seed": int(r.seed),
                    "reason": str(r.metrics.get("error") or "(no reason recorded)")}
    return None


def eval_info(records: list[EpisodeRecord]) -> dict:
    """LeRobot-style eval info of ONE policy/checkpoint's episodes."""
    if not records:
        raise ValueError("eval_info needs at least one episode record")
    labels = {(r.policy, r.checkpoint) for r in records}
    if len(labels) != 1:
        raise ValueError(f"eval_info takes the episodes of one policy/checkpoint, got {sorted(labels)}")
    recs = sorted(records, key=lambda r: (r.init_state, r.seed))
    per_episode = []
    for i, r in enumerate(recs):
        ep = {
            "episode_ix": i,
            "sum_reward": float(r.metrics.get("sum_reward", float("nan"))),
            "max_reward": float(r.metrics.get("max_reward", float("nan"))),
            "success": bool(r.success),
            "seed": int(r.seed),
            "init_state": int(r.init_state),
            "status": r.status,
        }
        if r.status != "ok":
            ep["error"] = str(r.metrics.get("error") or "")
        if r.metrics.get("final"):
            ep["final_metrics"] = r.metrics["final"]
        per_episode.append(ep)
    n = len(per_episode)
    eval_s = float(sum(r.wall_time_s for r in recs))
    sums, maxes = [e["sum_reward"] for e in per_episode], [e["max_reward"] for e in per_episode]
    successes = [e["success"] for e in per_episode]
    videos = [r.video_path for r in recs if r.video_path]
    group = {"avg_sum_reward": _nanmean(sums), "avg_max_reward": _nanmean(maxes),
             "pc_success": 100.0 * sum(successes) / n, "n_episodes": n,
             "video_paths": videos, "predicted_video_paths": []}
    task = recs[0].task
    n_errors = sum(r.status != "ok" for r in recs)
    return {
        "policy": recs[0].policy, "checkpoint": recs[0].checkpoint, "train_step": recs[0].train_step,
        "task": task,
        "per_task": [{"task_group": task, "task_id": 0, "metrics": {
            "sum_rewards": sums, "max_rewards": maxes, "successes": successes, "video_paths": videos,
            "predicted_video_paths": []}}],
        "per_group": {task: group},
        "overall": {**group, "eval_s": eval_s, "eval_ep_s": eval_s / n},
        "errors": {"n_errors": n_errors, "n_episodes": n, "first_error": first_error(recs)},
        # the older layout (kept for readers of `aggregated` / `per_episode`)
        "per_episode": per_episode,
        "aggregated": {"avg_sum_reward": group["avg_sum_reward"], "avg_max_reward": group["avg_max_reward"],
                       "pc_success": group["pc_success"], "eval_s": eval_s, "eval_ep_s": eval_s / n},
        "video_paths": videos,
    }


def policy_folder(policy: str, checkpoint: str) -> str:
    """File-system-safe folder name of a policy/checkpoint pair (eval_info and videos): one path component,
    never '.', '..' or hidden (a leading '.' becomes '_')."""
    name = re.sub(r"[^A-Za-z0-9_.\-]+", "-", policy + (f"_{checkpoint}" if checkpoint else ""))
    return "_" + name[1:] if name.startswith(".") else (name or "_")


def group_by_policy(records: list[EpisodeRecord]) -> dict[tuple[str, str], list[EpisodeRecord]]:
    """{(policy, checkpoint): records}, in the records' order."""
    groups: dict[tuple[str, str], list[EpisodeRecord]] = {}
    for r in records:
        groups.setdefault((r.policy, r.checkpoint), []).append(r)
    return groups


def write_eval_infos(records: list[EpisodeRecord], out_dir: str | Path) -> list[Path]:
    """Write `<out_dir>/<policy>[_<checkpoint>]/eval_info.json` per policy/checkpoint; returns the paths."""
    paths = []
    for (policy, ckpt), recs in sorted(group_by_policy(records).items()):
        path = Path(out_dir) / policy_folder(policy, ckpt) / "eval_info.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(eval_info(recs), indent=2, allow_nan=True))
        paths.append(path)
    return paths
