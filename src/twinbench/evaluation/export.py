"""`eval_info.json` in the shape LeRobot's eval script (`lerobot_eval.py`, `eval_policy`) writes.

Matched fields: `per_episode` = [{"episode_ix", "sum_reward", "max_reward", "success", "seed"}],
`aggregated` = {"avg_sum_reward", "avg_max_reward", "pc_success" (percent), "eval_s", "eval_ep_s"}
(nan-means, as LeRobot's `np.nanmean`), and `video_paths`. Differences, by necessity: episodes come
from parallel workers and possibly several resumed sessions, so `eval_s` is the sum of the episodes'
own wall times (not one wall-clock span) and `eval_ep_s = eval_s / n_episodes`; episodes are ordered
by (init_state, seed); an episode that ended in an error counts as a failure here (its status is in
the extra `status` field; the results store keeps it separate). Extra fields: `policy`,
`checkpoint`, `train_step`, per-episode `init_state` and `status`.
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


def eval_info(records: list[EpisodeRecord]) -> dict:
    """LeRobot-style eval info of ONE policy/checkpoint's episodes."""
    if not records:
        raise ValueError("eval_info needs at least one episode record")
    labels = {(r.policy, r.checkpoint) for r in records}
    if len(labels) != 1:
        raise ValueError(f"eval_info takes the episodes of one policy/checkpoint, got {sorted(labels)}")
    recs = sorted(records, key=lambda r: (r.init_state, r.seed))
    per_episode = [{
        "episode_ix": i,
        "sum_reward": float(r.metrics.get("sum_reward", float("nan"))),
        "max_reward": float(r.metrics.get("max_reward", float("nan"))),
        "success": bool(r.success),
        "seed": int(r.seed),
        "init_state": int(r.init_state),
        "status": r.status,
    } for i, r in enumerate(recs)]
    eval_s = float(sum(r.wall_time_s for r in recs))
    return {
        "policy": recs[0].policy, "checkpoint": recs[0].checkpoint, "train_step": recs[0].train_step,
        "per_episode": per_episode,
        "aggregated": {
            "avg_sum_reward": _nanmean([e["sum_reward"] for e in per_episode]),
            "avg_max_reward": _nanmean([e["max_reward"] for e in per_episode]),
            "pc_success": 100.0 * sum(e["success"] for e in per_episode) / len(per_episode),
            "eval_s": eval_s,
            "eval_ep_s": eval_s / len(per_episode),
        },
        "video_paths": [r.video_path for r in recs if r.video_path],
    }


def policy_folder(policy: str, checkpoint: str) -> str:
    """File-system-safe folder name of a policy/checkpoint pair (eval_info and videos): one path component,
    never '.', '..' or hidden (a leading '.' becomes '_')."""
    name = re.sub(r"[^A-Za-z0-9_.\-]+", "-", policy + (f"_{checkpoint}" if checkpoint else ""))
    return "_" + name[1:] if name.startswith(".") else (name or "_")


def write_eval_infos(records: list[EpisodeRecord], out_dir: str | Path) -> list[Path]:
    """Write `<out_dir>/<policy>[_<checkpoint>]/eval_info.json` per policy/checkpoint; returns the paths."""
    groups: dict[tuple[str, str], list[EpisodeRecord]] = {}
    for r in records:
        groups.setdefault((r.policy, r.checkpoint), []).append(r)
    paths = []
    for (policy, ckpt), recs in sorted(groups.items()):
        path = Path(out_dir) / policy_folder(policy, ckpt) / "eval_info.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(eval_info(recs), indent=2, allow_nan=True))
        paths.append(path)
    return paths
