"""The scripted experts over their tasks' whole grids: one episode per grid state (seed 0), in worker
processes, one line per state as it finishes (success under the success rule, the task's final metric,
steps, wall seconds) and a summary line per task, `TASK_PRESET_expert_success K/N`.

    PYTHONPATH=src python benchmarks/expert_grid.py --preset fast --workers 2
    PYTHONPATH=src python benchmarks/expert_grid.py --tasks rope-routing --states 0 13 --rule early
    PYTHONPATH=src python benchmarks/expert_grid.py --preset reference --workers 16 --no-images

Final metrics: push-T the mean squared particle distance to the goal (success below 0.002 m^2), rope
routing the springs crossing each opening (and the threshold), toy packing the particles inside the box.
`--no-images`: each camera renders once (the first observation) and keeps that frame: the experts act
from the privileged state only, so outcomes are the same, 1.5-4x faster on CPU.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor, as_completed

TASKS = ("push-t", "rope-routing", "toy-packing")
_ENVS: dict = {}  # per worker process: (task, env kwargs) -> env


def final_metric(task: str, final: dict, n_particles: int) -> str:
    """The task's final metric as text."""
    if "msd" in final:
        return f"msd {final['msd']:.5f} m2"
    if "crossings" in final:
        a, b = final["crossings"]
        return f"crossings {int(a)}/{int(b)} (need {int(final['crossing_threshold'])})"
    if "inside_fraction" in final:
        inside = round(final["inside_fraction"] * n_particles)
        return f"inside {inside}/{n_particles} particles ({final['inside_fraction']:.4f})"
    return json.dumps(final)


def _env(task: str, env_kwargs: dict, images: bool):
    from twinbench.tasks import get_task

    key = (task, json.dumps(env_kwargs, sort_keys=True), images)
    if key not in _ENVS:
        env = get_task(task).make_env(environment_state=True, **env_kwargs)
        if not images:
            twin, kept = env.unwrapped.twin, {}
            real = twin.render

            def render(state, cameras=None):
                if not kept:
                    kept.update(real(state, cameras))
                return kept

            twin.render = render
        _ENVS[key] = env
    return _ENVS[key]


def run_state(task: str, state: int, seed: int, env_kwargs: dict, images: bool) -> dict:
    """One expert episode from grid state `state` (in a worker process) -> its outcome as a dict."""
    from twinbench.evaluation.rollout import run_episode
    from twinbench.tasks import get_task

    env = _env(task, env_kwargs, images)
    expert = get_task(task).make_expert(env)
    out = run_episode(env, expert, init_state=state, seed=seed)
    roles = env.unwrapped.rules.roles
    n = len(env.unwrapped.twin.rest_particles(roles["toy"])) if "toy" in roles else 0
    return {"task": task, "state": state, "success": out.success, "status": out.status, "steps": out.steps,
            "wall_s": out.wall_time_s, "metric": final_metric(task, out.final or {}, n),
            "error": out.error}


def _init_worker(cores: str) -> None:
    from twinbench._runtime import CPU_THREADS_ENV, quiet_warp, watch_parent

    os.environ[CPU_THREADS_ENV] = cores
    watch_parent()
    quiet_warp()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="+", default=list(TASKS))
    p.add_argument("--preset", default="fast")
    p.add_argument("--states", nargs="+", type=int, default=None, help="grid states (default: all)")
    p.add_argument("--workers", type=int, default=1, help="worker processes (0: this process)")
    p.add_argument("--rule", choices=("final", "early"), default="final", help="the env's success rule")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-images", action="store_true", help="render each camera once (see above)")
    p.add_argument("--env-kwargs", type=json.loads, default={},
                   help="JSON object of more env keyword arguments, e.g. '{\"episode_seconds\": 30}'")
    args = p.parse_args()
    from twinbench._runtime import quiet_warp, share_cores
    from twinbench.tasks import get_task

    quiet_warp()
    env_kwargs = {"preset": args.preset, "success_rule": args.rule, **args.env_kwargs}
    jobs = []
    for task in args.tasks:
        n = get_task(task).n_grid_states
        states = range(n) if args.states is None else [s for s in args.states if 0 <= s < n]
        jobs += [(task, s, args.seed, env_kwargs, not args.no_images) for s in states]
    results: dict[str, list[dict]] = {task: [] for task in args.tasks}
    t0 = time.perf_counter()

    def report(r: dict) -> None:
        results[r["task"]].append(r)
        err = f" {r['status']}: {r['error']}" if r["status"] != "ok" else ""
        print(f"{r['task']} {args.preset} state {r['state']:2d}: success {int(r['success'])} {r['metric']} "
              f"steps {r['steps']} wall {r['wall_s']:.1f} s{err}", flush=True)

    if args.workers == 0:
        for job in jobs:
            report(run_state(*job))
    else:
        cores = share_cores(args.workers)
        import multiprocessing as mp

        with ProcessPoolExecutor(args.workers, mp_context=mp.get_context("spawn"), initializer=_init_worker,
                                 initargs=(cores,)) as pool:
            for fut in as_completed([pool.submit(run_state, *job) for job in jobs]):
                report(fut.result())
    for task in args.tasks:
        rs = sorted(results[task], key=lambda r: r["state"])
        failed = [r["state"] for r in rs if not r["success"]]
        print(f"{task}_{args.preset}_expert_success {sum(r['success'] for r in rs)}/{len(rs)} "
              f"(rule {args.rule}; failed states {failed})", flush=True)
    print(f"expert_grid wall {time.perf_counter() - t0:.0f} s", flush=True)


if __name__ == "__main__":
    main()
