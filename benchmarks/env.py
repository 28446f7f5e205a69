"""Push-T env speed: env steps per second with two 240x240 cameras, split into physics (controller +
spring-mass frame) and rendering (Gaussian posing + both cameras), for the `fast` and `reference`
built-in cells, on CPU and on CUDA when present.

Prints `name value unit` lines (medians over the timed steps, after warm-up steps).
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp

from twinbench.env import TwinEnv
from twinbench.evaluation.runner import policy_observation
from twinbench.tasks.push_t_expert import PushTExpert


def bench(preset: str, device: str, steps: int, warmup: int = 5) -> None:
    env = TwinEnv("push-t", preset=preset, device=device)
    obs, info = env.reset(seed=0, options={"init_state": 0})
    expert = PushTExpert(env.rules.shape)
    twin, state = env.twin, env.state
    physics, render, total = [], [], []
    for k in range(warmup + steps):
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
            total.append(t1 - t0)
            physics.append(t2 - t1)
            render.append(t3 - t2)
    tag = f"pusht_{preset}_{device.replace(':', '')}"
    print(f"{tag}_env_steps_per_s {1.0 / np.median(total):.2f} steps/s")
    print(f"{tag}_physics_ms {1e3 * np.median(physics):.1f} ms")
    print(f"{tag}_render_2cams_240_ms {1e3 * np.median(render):.1f} ms")
    print(f"{tag}_block_particles {twin.model.num_particles} particles")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=30)
    parser.add_argument("--presets", nargs="+", default=["fast", "reference"])
    args = parser.parse_args()
    wp.config.quiet = True
    devices = ["cpu"] + (["cuda:0"] if wp.get_cuda_device_count() > 0 else [])
    for device in devices:
        for preset in args.presets:
            bench(preset, device, args.steps if preset == "fast" else max(args.steps // 3, 5))


if __name__ == "__main__":
    main()
