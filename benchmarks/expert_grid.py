"""The scripted experts over their tasks' whole grids: one episode per grid state (seed 0), run by the
evaluation runner's worker processes, one line per state as it finishes (success under the success rule,
the task's final metric, steps, wall seconds) and a summary line per task, `TASK_PRESET_expert_success K/N`.

    PYTHONPATH=src python benchmarks/expert_grid.py --preset fast --workers 2
    PYTHONPATH=src python benchmarks/expert_grid.py --tasks rope-routing --states 0 13 --rule early
    PYTHONPATH=src python benchmarks/expert_grid.py --preset reference --workers 16 --no-images

Final metrics: push-T the mean squared particle distance to the goal (success below 0.002 m^2), rope
routing the springs crossing each opening (and the threshold), toy packing the particles inside the box.
`--no-images` renders no camera (the env's `cameras=""`): the experts act from the privileged state only,
so the outcomes are the same, 1.5-4x faster on CPU.
"""

from __future__ import annotations

import argparse
import json
import time

TASKS = ("push-t", "rope-routing", "toy-packing")


def final_metric(final: dict, n_particles: int | None) -> str:
    """The task's final metric (the episode's `metrics["final"]`) as text."""
    if "msd" in final:
        return f"msd {final['msd']:.5f} m2"
    if "crossings" in final:
        a, b = final["crossings"]
        return f"crossings {int(a)}/{int(b)} (need {int(final['crossing_threshold'])})"
    if "inside_fraction" in final and n_particles:
        inside = round(final["inside_fraction"] * n_particles)
        return f"inside {inside}/{n_particles} particles ({final['inside_fraction']:.4f})"
    return json.dumps(final)


def toy_particles(task: str, preset: str) -> int | None:
    """Particles of a task's `toy` (the built-in cell at `preset`), None for a task without one."""
    from twinbench.tasks import get_task

    rules = get_task(task).task_cls()
    if "toy" not in rules.roles:
        return None
    return len(rules.default_twin(preset).object(rules.roles["toy"]).particles)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="+", default=list(TASKS))
    p.add_argument("--preset", default="fast")
    p.add_argument("--states", nargs="+", type=int, default=None, help="grid states (default: all)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (0: this process)")
    p.add_argument("--rule", choices=("final", "early"), default="final", help="the env's success rule")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-images", action="store_true", help="render no camera (see above)")
    p.add_argument("--env-kwargs", type=json.loads, default={},
                   help="JSON object of more env keyword arguments, e.g. '{\"episode_seconds\": 30}'")
    args = p.parse_args()
    from twinbench._runtime import quiet_warp
    from twinbench.evaluation.backends import run_local
    from twinbench.evaluation.rollout import EpisodeBatch, EpisodeJob
    from twinbench.tasks import get_task

    quiet_warp()
    env_kwargs = {"preset": args.preset, "success_rule": args.rule, **args.env_kwargs}
    if args.no_images:
        env_kwargs["cameras"] = ""
    batches = []
    for task in args.tasks:
        n = get_task(task).n_grid_states
        states = range(n) if args.states is None else [s for s in args.states if 0 <= s < n]
        batches += [EpisodeBatch((EpisodeJob(task, "expert", s, args.seed, "expert_grid", env_kwargs),))
                    for s in states]
    particles = {task: toy_particles(task, args.preset) for task in args.tasks}
    results: dict[str, list] = {task: [] for task in args.tasks}
    t0 = time.perf_counter()

    def report(rec) -> None:
        results[rec.task].append(rec)
        err = f" {rec.status}: {rec.metrics.get('error')}" if rec.status != "ok" else ""
        metric = final_metric(rec.metrics.get("final") or {}, particles[rec.task])
        print(f"{rec.task} {args.preset} state {rec.init_state:2d}: success {int(rec.success)} {metric} "
              f"steps {rec.steps} wall {rec.wall_time_s:.1f} s{err}", flush=True)

    run_local(batches, args.workers, report)
    for task in args.tasks:
        recs = sorted(results[task], key=lambda r: r.init_state)
        failed = [r.init_state for r in recs if not r.success]
        print(f"{task}_{args.preset}_expert_success {sum(r.success for r in recs)}/{len(recs)} "
              f"(rule {args.rule}; failed states {failed})", flush=True)
    print(f"expert_grid wall {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
