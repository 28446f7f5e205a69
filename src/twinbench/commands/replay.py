"""`twinbench replay`: replay recorded real rollouts open-loop in the twin and print replay-vs-real
confusion matrices."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from twinbench.commands.env_options import env_kwargs_with_twin, parse_env_kwargs
from twinbench.evaluation.replay import load_recorded, replay_confusion, replay_episodes
from twinbench.evaluation.store import DEFAULT_DB


@dataclass(frozen=True)
class ReplayConfig:
    """Replay recorded real rollouts open-loop in the twin; print replay-vs-real confusion matrices."""

    source: Path
    """LeRobotDataset v3 folder, or a .json / .npz log (schemas: twinbench.evaluation.replay); a JSON log
    may give robot logs (ee_poses or joint_positions per frame) instead of actions, and measured start
    poses of the objects (object_poses)"""
    task: str = "point-reach"
    run_id: str = "replay"
    db: Path = DEFAULT_DB
    outcomes: Path | None = None
    """JSON with per-episode init_state/success/policy/checkpoint for a LeRobotDataset lacking them"""
    env_kwargs: str = ""
    """JSON dict of extra gymnasium.make keyword arguments"""
    twin: Path | None = None
    """a twin directory to replay in (default: the task's built-in cell)"""
    index_map: Path | None = None
    """CSV (study_index,init_state) or JSON map from the recording's init_state values to the task's grid
    indices; not needed for the reference study's indices (the built-in grids are in its order)"""
    workers: int = 0
    """worker processes replaying episodes side by side (0: in this process); a run re-run with the same
    --run-id replays only the episodes it does not hold yet"""


def main(cfg: ReplayConfig) -> int:
    env_kwargs = env_kwargs_with_twin(parse_env_kwargs(cfg.env_kwargs), cfg.twin, cfg.task)
    episodes = load_recorded(cfg.source, cfg.outcomes)
    pairs = replay_episodes(cfg.task, episodes, cfg.db, cfg.run_id, env_kwargs=env_kwargs,
                            index_map=cfg.index_map, workers=cfg.workers)
    print(f"replayed {len(pairs)} episodes of {cfg.source} in {cfg.task} (run {cfg.run_id!r}, {cfg.db})")
    for by in ("checkpoint", "task"):
        for key, c in replay_confusion(cfg.db, cfg.run_id, by=by).items():
            print(f"{' / '.join(str(k) for k in key if k != '') or '-'}: TP={c.tp} FP={c.fp} FN={c.fn} "
                  f"TN={c.tn} accuracy={c.accuracy:.3f} excluded={c.excluded}")
    return 0
