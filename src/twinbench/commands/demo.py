"""`make demo` / `twinbench demo`: evaluate scripted policies on a few grid states of a task's built-in
twin (CPU), with a video per episode and the HTML report.

- push-t (the default, `make demo`): the expert and a degraded copy of it (`expert@0.5`) on four states;
- `--task rope-routing`, `--task toy-packing`: the expert on three states of the soft-body cells.

The `fast` presets are used, push-T episodes last 20 s (not 60), and episodes end once the success window
holds (`success_rule="early"`); the report names the rule. The run is resumable like any evaluation:
running the demo again reuses the finished episodes (delete `OUT_DIR` to start over).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

# task -> (grid states, policies, episode seconds: push-T's 60 s would make each failed episode 1,800 steps)
DEFAULTS = {
    "push-t": ("grid:0,5,10,15", ("expert", "expert@0.5"), 20.0),
    "rope-routing": ("grid:4,13,22", ("expert",), None),
    "toy-packing": ("grid:2,9,16", ("expert",), None),
}


@dataclass(frozen=True)
class DemoConfig:
    """Evaluation demo on a task's built-in twin."""

    task: str = "push-t"
    """push-t, rope-routing or toy-packing"""
    out_dir: Path | None = None
    """results store, videos, eval_info.json files and report.html (default: outputs/demo, or
    outputs/demo-TASK for the soft-body tasks)"""
    episodes: str | None = None
    """initial states: 'grid', 'grid:I,J,...' or N sampled states (default: a few grid states)"""
    policies: tuple[str, ...] | None = None
    """policy specs (default: push-t: the expert and a degraded copy; otherwise the expert)"""
    preset: str = "fast"
    """twin preset: 'fast' (coarser particles, fewer substeps) or 'reference'"""
    workers: int = 2
    success_rule: str = "early"
    """'early' ends an episode once the success window holds (quick); 'final' runs the whole episode and
    judges its last 100 frames (the reference rule)"""
    run_id: str | None = None
    """default: demo (push-t) or demo-TASK"""
    device: str = "cpu"
    episode_seconds: float | None = None
    """episode length (default: 20 s for push-t, whose task length is 60 s; the task's own otherwise)"""


def main(cfg: DemoConfig) -> int:
    from twinbench.evaluation.report import write_report
    from twinbench.evaluation.runner import EvaluationInterrupted, evaluate
    from twinbench.evaluation.store import ResultsStore

    if cfg.task not in DEFAULTS:
        raise ValueError(f"--task must be one of {sorted(DEFAULTS)}, got {cfg.task!r}")
    episodes, policies, seconds = DEFAULTS[cfg.task]
    seconds = cfg.episode_seconds or seconds
    suffix = "" if cfg.task == "push-t" else f"-{cfg.task}"
    out = Path(cfg.out_dir or f"outputs/demo{suffix}")
    run_id = cfg.run_id or f"demo{suffix}"
    out.mkdir(parents=True, exist_ok=True)
    store = ResultsStore(out / "results.sqlite")
    t0 = time.perf_counter()
    try:
        records = evaluate(
            cfg.task,
            list(cfg.policies or policies),
            cfg.episodes or episodes,
            cfg.workers,
            run_id,
            store,
            video=True,
            output_dir=out,
            progress=True,
            log=print,
            env_kwargs={
                **({"episode_seconds": seconds} if seconds else {}),
                "preset": cfg.preset,
                "render_views": "front+wrist",
                "device": cfg.device,
                "success_rule": cfg.success_rule,
            },
        )
    except EvaluationInterrupted as err:
        print(err.message)
        return 130
    report = write_report(store, run_id, out / "report.html")
    print(f"\n{cfg.task} demo ({cfg.preset} twin, {time.perf_counter() - t0:.0f} s):")
    for r in records:
        label = r.policy + (f"@{r.checkpoint}" if r.checkpoint else "")
        outcome = "success" if r.success else ("failure" if r.status == "ok" else r.status)
        print(f"  {label:<22} init_state {r.init_state:>2}: {outcome:<8} {r.steps:>4} steps  {r.video_path}")
    print(f"\nvideos: {out / 'videos' / run_id}\nreport: {report}")
    return 0
