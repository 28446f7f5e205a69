"""`make demo` / `twinbench demo`: evaluate the scripted push-T expert and a degraded copy of it on four
grid states of the built-in twin (CPU), with a video per episode and the HTML report.

The run is resumable like any evaluation: running the demo again reuses the finished episodes (delete
`OUT_DIR` to start over).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class DemoConfig:
    """Push-T evaluation demo on the built-in twin."""

    out_dir: Path = Path("outputs/demo")
    """results store, videos, eval_info.json files and report.html go here"""
    episodes: str = "grid:0,5,10,15"
    """initial states: 'grid', 'grid:I,J,...' or N sampled states"""
    policies: tuple[str, ...] = ("expert", "expert@0.5")
    """policy specs (the expert and a degraded copy of it)"""
    preset: str = "fast"
    """push-t twin preset: 'fast' (15 mm block lattice, 100 substeps) or 'reference'"""
    workers: int = 2
    success_rule: str = "early"
    """'early' ends an episode once the success window holds (quick); 'final' runs the full 60 s and judges
    the last 100 frames (the reference rule)"""
    run_id: str = "demo"
    device: str = "cpu"


def main(cfg: DemoConfig) -> int:
    from twinbench.evaluation.report import write_report
    from twinbench.evaluation.runner import EvaluationInterrupted, evaluate
    from twinbench.evaluation.store import ResultsStore

    out = Path(cfg.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    store = ResultsStore(out / "results.sqlite")
    t0 = time.perf_counter()
    try:
        records = evaluate(
            "push-t", list(cfg.policies), cfg.episodes, cfg.workers, cfg.run_id, store,
            video=True, output_dir=out, progress=True, log=print,
            env_kwargs={"preset": cfg.preset, "render_views": "front+wrist", "device": cfg.device,
                        "success_rule": cfg.success_rule},
        )
    except EvaluationInterrupted as err:
        print(err.message)
        return 130
    report = write_report(store, cfg.run_id, out / "report.html")
    print(f"\npush-t demo ({cfg.preset} twin, {time.perf_counter() - t0:.0f} s):")
    for r in records:
        label = r.policy + (f"@{r.checkpoint}" if r.checkpoint else "")
        outcome = "success" if r.success else ("failure" if r.status == "ok" else r.status)
        print(f"  {label:<22} init_state {r.init_state:>2}: {outcome:<8} {r.steps:>4} steps  {r.video_path}")
    print(f"\nvideos: {out / 'videos' / cfg.run_id}\nreport: {report}")
    return 0
