"""`twinbench eval`: evaluate policies on a task over its initial-state grid (parallel, resumable).

Exit status: 0 when the run finished and every policy had at least one episode without an error; 1 when
every episode of some policy ended in an error (policy_error / sim_error: the first error's reason is
printed per policy and written to its eval_info.json); 130 / 143 when interrupted (SIGINT / SIGTERM)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

from tyro.conf import UseAppendAction

from twinbench.commands.env_options import env_kwargs_with_twin, parse_env_kwargs
from twinbench.evaluation.export import first_error, group_by_policy
from twinbench.evaluation.runner import EvaluationInterrupted, EvaluationTerminated, evaluate
from twinbench.evaluation.store import DEFAULT_DB


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
    """write an MP4 per episode under OUTPUT_DIR/videos/RUN_ID/ (cameras: --video-views)"""
    video_views: str = "all"
    """cameras each video shows side by side: 'all' (every camera) or names joined by '+', e.g. 'front'"""
    record_actions: bool = False
    """write each episode's commanded actions (.npy) under OUTPUT_DIR/actions/RUN_ID/, e.g. for replay"""
    policy_timeout: float | None = None
    """seconds per policy call for remote policies (default: the policy's own, 30 s); a warm-up request
    is sent before the first episode either way"""
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
    env_kwargs = env_kwargs_with_twin(parse_env_kwargs(cfg.env_kwargs), cfg.twin, cfg.task)
    try:
        records = evaluate(cfg.task, list(cfg.policy), cfg.episodes, cfg.workers, cfg.run_id, cfg.db,
                           seed=cfg.seed, video=cfg.video, backend=cfg.backend, output_dir=cfg.output_dir,
                           env_kwargs=env_kwargs, retry_errors=cfg.retry_errors, progress=cfg.progress,
                           log=say, worlds=cfg.worlds, video_views=cfg.video_views,
                           policy_timeout_s=cfg.policy_timeout, record_actions=cfg.record_actions)
    except EvaluationInterrupted as err:
        say(err.message)
        return 143 if isinstance(err, EvaluationTerminated) else 130
    all_failed = []
    for (name, ckpt), recs in group_by_policy(records).items():
        ok = sum(r.success for r in recs)
        errs = sum(r.status != "ok" for r in recs)
        label = name + (f" [{ckpt}]" if ckpt else "")
        say(f"{label}: {ok}/{len(recs)} successes ({100 * ok / len(recs):.1f}%), {errs} errors")
        first = first_error(recs)
        if first is not None:
            say(f"  first error ({first['status']}, init_state {first['init_state']}, seed {first['seed']}): "
                f"{first['reason']}")
        if errs == len(recs):
            all_failed.append(label)
    say(f"eval_info.json files under {cfg.output_dir / 'eval' / cfg.run_id}")
    if all_failed:
        say(f"twinbench eval: every episode of {', '.join(all_failed)} ended in an error (exit status 1)")
        return 1
    return 0
