"""Env speed: env steps per second with two 240x240 cameras, split into physics (controller + spring-mass
frame) and rendering (Gaussian posing + both cameras), for the `fast` and `reference` built-in cells of
push-T, rope routing and toy packing (scripted-expert actions), on CPU and on CUDA when present; the
`reference` cells on CPU run twice, on one core and split over two (TWINBENCH_CPU_THREADS=1 / 2).

Many worlds (`--worlds`, default 1 4 16 64): `fast` push-T as the worlds of one TwinVectorEnv, the
pusher of world i sweeping a circle from its own grid state; world-steps per second for physics only
(`Twin.step_worlds`: controllers + one spring-mass frame for all worlds, on every core) and for whole env
steps with both cameras of every world rendered; and rendering alone, ms per world, for all worlds'
cameras in one `Twin.render_worlds` call against one `Twin.render` call per world (render cache off).

Render cache A/B (`Twin.render_cache`, the static scene's work kept per unmoved camera): the env steps and
renders alternate between the cache on and off in one run (the state is the same either way); `*_cache_off`
lines give the figures without it (on CUDA, where twins render without it by default, the plain lines use
a cache made for the A/B).

Prints `name value unit` lines (medians over the timed steps, after warm-up steps).
"""

from __future__ import annotations

import argparse
import os
import time

import numpy as np
import warp as wp

from twinbench._runtime import quiet_warp
from twinbench.env import TwinEnv, TwinVectorEnv
from twinbench.evaluation.rollout import policy_observation
from twinbench.gaussians.render import RenderCache
from twinbench.tasks import get_task

TASKS = {"push-t": "pusht", "rope-routing": "rope", "toy-packing": "toy"}


def bench(task: str, preset: str, device: str, steps: int, warmup: int = 5, cores: int | None = None) -> None:
    if cores is not None:  # the solver reads it when the env is built
        os.environ["TWINBENCH_CPU_THREADS"] = str(cores)
    env = TwinEnv(task, preset=preset, device=device)
    os.environ.pop("TWINBENCH_CPU_THREADS", None)
    obs, info = env.reset(seed=0, options={"init_state": 0})
    expert = get_task(task).make_expert(env)
    twin, state = env.twin, env.state
    cache = twin.render_cache or RenderCache()  # on CUDA twins render without it by default
    physics, render, total = [], {True: [], False: []}, {True: [], False: []}
    for k in range(warmup + 2 * steps):
        on = k % 2 == 0  # A/B: the render cache on in even steps, off in odd ones (the state is the same)
        twin.render_cache = cache if on else None
        action = expert.select_action(policy_observation(expert, obs, info))
        t0 = time.perf_counter()
        obs, _, _, _, info = env.step(action)
        t1 = time.perf_counter()
        # Split: the same step again (from the new state) timed part by part.
        twin.step(state, action)
        t2 = time.perf_counter()
        twin.render(state)
        t3 = time.perf_counter()
        if k >= warmup:
            total[on].append(t1 - t0)
            physics.append(t2 - t1)
            render[on].append(t3 - t2)
    twin.render_cache = cache
    tag = f"{TASKS[task]}_{preset}_{device.replace(':', '')}" + (f"_{cores}cores" if cores else "")
    print(f"{tag}_env_steps_per_s {1.0 / np.median(total[True]):.2f} steps/s")
    print(f"{tag}_env_steps_per_s_cache_off {1.0 / np.median(total[False]):.2f} steps/s")
    print(f"{tag}_physics_ms {1e3 * np.median(physics):.1f} ms")
    print(f"{tag}_render_2cams_240_ms {1e3 * np.median(render[True]):.1f} ms")
    print(f"{tag}_render_2cams_240_ms_cache_off {1e3 * np.median(render[False]):.1f} ms")
    print(f"{tag}_particles {twin.model.num_particles} particles")
    if cores:  # whether this world's frames were split over two processes (large models only)
        print(f"{tag}_split_frames {int(twin.solver.executor.name == 'split')} bool")


def bench_worlds(device: str, counts: list[int], steps: int, render_steps: int) -> None:
    for n in counts:
        envs = TwinVectorEnv("push-t", n, preset="fast", device=device)
        obs, _ = envs.reset(seed=0, options={"init_state": [i % 16 for i in range(n)]})
        start = obs["agent_pos"].astype(np.float64)
        phase = np.arange(n)[:, None] * 0.7

        def actions(k: int, start=start, phase=phase) -> np.ndarray:
            angle = 0.15 * k + phase
            return (start + 0.02 * np.concatenate([np.cos(angle), np.sin(angle)], axis=1)).astype(np.float32)

        states = [env.state for env in envs.envs]
        physics = []
        for k in range(3 + steps):
            t0 = time.perf_counter()
            envs.twin.step_worlds(states, list(actions(k)))
            if k >= 3:
                physics.append(time.perf_counter() - t0)
        # every world's two cameras: one render_worlds call / a call per world (cache off: the same states
        # rendered again would find even the wrist cameras kept)
        cache, envs.twin.render_cache = envs.twin.render_cache or RenderCache(), None
        batched, one_by_one = [], []
        for k in range(1 + render_steps):
            t0 = time.perf_counter()
            envs.twin.render_worlds(states)
            t1 = time.perf_counter()
            for state in states:
                envs.twin.render(state)
            if k >= 1:
                batched.append(t1 - t0)
                one_by_one.append(time.perf_counter() - t1)
        full: dict = {True: [], False: []}
        for k in range(2 + 2 * render_steps):  # A/B: the render cache on in even steps, off in odd ones
            on = k % 2 == 0
            envs.twin.render_cache = cache if on else None
            t0 = time.perf_counter()
            envs.step(actions(k))
            if k >= 2:
                full[on].append(time.perf_counter() - t0)
        envs.twin.render_cache = cache
        tag = f"pusht_fast_{device.replace(':', '')}_{n}worlds"
        print(f"{tag}_physics_world_steps_per_s {n / np.median(physics):.0f} world-steps/s")
        print(f"{tag}_render_ms_per_world {1e3 * np.median(batched) / n:.1f} ms")
        print(f"{tag}_render_ms_per_world_one_call_each {1e3 * np.median(one_by_one) / n:.1f} ms")
        print(f"{tag}_env_world_steps_per_s {n / np.median(full[True]):.1f} world-steps/s")
        print(f"{tag}_env_world_steps_per_s_cache_off {n / np.median(full[False]):.1f} world-steps/s")
        print(f"{tag}_threads {envs.twin.solver.threads} threads")
        envs.close()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--presets", nargs="+", default=["fast", "reference"])
    parser.add_argument("--tasks", nargs="+", default=list(TASKS), choices=list(TASKS))
    parser.add_argument("--worlds", nargs="*", type=int, default=[1, 4, 16, 64])
    parser.add_argument("--world-steps", type=int, default=10,
                        help="timed many-world steps with the render cache on (and as many off) per count")
    args = parser.parse_args()
    quiet_warp()  # no per-module load lines
    devices = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
    for device in devices:
        for task in args.tasks:
            for preset in args.presets:
                steps = args.steps if preset == "fast" else max(args.steps // 3, 5)
                if device == "cpu" and preset == "reference":  # one world on one core, then split over two
                    for cores in (1, 2):
                        bench(task, preset, device, steps, cores=cores)
                else:
                    bench(task, preset, device, steps)
        bench_worlds(device, args.worlds, args.steps, args.world_steps)


if __name__ == "__main__":
    main()
