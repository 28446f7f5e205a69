"""`twinbench eval`: evaluate policies on a task over its initial-state grid (parallel, resumable)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from tyro.conf import UseAppendAction

from twinbench.commands.env_options import env_kwargs_with_twin, parse_env_kwargs
from twinbench.evaluation.runner import EvaluationInterrupted, EvaluationTerminated, evaluate
from twinbench.evaluation.store import DEFAULT_DB, EpisodeRecord


@dataclass(frozen=True)
class EvalConfig:
    """Evaluate policies on a task over its initial-state grid (or N sampled states)."""

    run_id: str
    """evaluation run id; re-running the same id resumes it"""
    task: str = "push-t"
    """task name (twinbench.tasks): push-t, rope-routing, toy-packing, point-reach (a cheap debug task)"""
    policy: Annotated[tuple[str, ...], UseAppendAction] = ()  # repeatable: --policy a --policy b
    """policy spec, repeatable: expert, expert@LEVEL, remote:ws://HOST:PORT, lerobot:PATH, NAME=SPEC"""
    episodes: str = "grid"
    """'grid' (the task's initial-state grid), 'grid:I,J,...' (some grid states) or N (N sampled states)"""
    workers: int = 1
    """worker processes (0 = run in this process)"""
    db: Path = DEFAULT_DB
    video: bool = False
    """write an MP4 per episode under OUTPUT_DIR/videos/RUN_ID/"""
    backend: Literal["local", "ray"] = "local"
    seed: int = 0
    output_dir: Path = Path("outputs")
    env_kwargs: str = ""
    """JSON dict of extra gymnasium.make keyword arguments for the task's env"""
    twin: Path | None = None
    """a twin directory to evaluate in (default: the task's built-in cell)"""
    worlds: int = 1
    """episodes run together as worlds of one many-world env (one physics launch for all), per worker"""
    retry_errors: bool = False
    """re-run episodes that ended in sim_error/policy_error"""
    progress: bool = True


def main(cfg: EvalConfig) -> int:
    from rich.console import Console

    console = Console(stderr=True)

    def say(msg: str) -> None:
        console.print(msg, markup=False, soft_wrap=True, highlight=False)

    if not cfg.policy:
        say("twinbench eval: give at least one --policy (e.g. --policy expert)")
        return 2
    env_kwargs = env_kwargs_with_twin(parse_env_kwargs(cfg.env_kwargs), cfg.twin)
    try:
        records = evaluate(cfg.task, list(cfg.policy), cfg.episodes, cfg.workers, cfg.run_id, cfg.db,
                           seed=cfg.seed, video=cfg.video, backend=cfg.backend, output_dir=cfg.output_dir,
                           env_kwargs=env_kwargs, retry_errors=cfg.retry_errors, progress=cfg.progress,
                           log=say, worlds=cfg.worlds)
    except EvaluationInterrupted as err:
        say(err.message)
        return 143 if isinstance(err, EvaluationTerminated) else 130
    by_policy: dict[tuple[str, str], list[EpisodeRecord]] = {}
    for r in records:
        by_policy.setdefault((r.policy, r.checkpoint), []).append(r)
    for (name, ckpt), recs in by_policy.items():
        ok = sum(r.success for r in recs)
        errs = sum(r.status != "ok" for r in recs)
        label = name + (f" [{ckpt}]" if ckpt else "")
        say(f"{label}: {ok}/{len(recs)} successes ({100 * ok / len(recs):.1f}%), {errs} errors")
    say(f"eval_info.json files under {cfg.output_dir / 'eval' / cfg.run_id}")
    return 0
