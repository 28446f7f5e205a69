"""Episode hashes: the scripted expert's first steps on every task and preset, hashed (observations,
rewards, success flags, particles). A refactor that claims "behaviour unchanged" prints the same lines
before and after.

    python benchmarks/episode_hashes.py                 # every task, presets fast and reference
    python benchmarks/episode_hashes.py --steps 20 --tasks push-t --presets fast
    python benchmarks/episode_hashes.py --tasks push-t --presets small-fast --init-state 3 \
        --env-kwargs '{"settle_steps": 0, "pusher_start": [0.30, 0.0]}'   # the cell before the study's layout
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time

import numpy as np


def episode_hash(task: str, preset: str, init_state: int, steps: int, env_kwargs: dict | None = None) -> str:
    from twinbench.tasks import get_task

    spec = get_task(task)
    env = spec.make_env(preset=preset, environment_state=True, **(env_kwargs or {}))
    expert = spec.make_expert(env)
    h = hashlib.sha256()
    obs, _ = env.reset(seed=0, options={"init_state": init_state})
    expert.reset()
    for _ in range(steps):
        action = expert.select_action(obs)
        obs, reward, _, _, info = env.step(action)
        for name in sorted(obs["pixels"]):
            h.update(np.ascontiguousarray(obs["pixels"][name]).tobytes())
        h.update(np.asarray(obs["agent_pos"], np.float32).tobytes())
        h.update(np.asarray(obs["environment_state"], np.float32).tobytes())
        h.update(np.float64(reward).tobytes() + bytes([bool(info["is_success"])]))
    twin, state = env.unwrapped.twin, env.unwrapped.state
    for name in twin.object_names:
        h.update(np.asarray(twin.particles(state, name), np.float32).tobytes())
    env.close()
    return h.hexdigest()[:16]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="+", default=["push-t", "rope-routing", "toy-packing"])
    p.add_argument("--presets", nargs="+", default=["fast", "reference"])
    p.add_argument("--steps", type=int, default=8)
    p.add_argument("--init-state", type=int, default=1)
    p.add_argument("--env-kwargs", type=json.loads, default={},
                   help="JSON object of env keyword arguments (task and cell settings), e.g. "
                   '\'{"settle_steps": 0}\'')
    args = p.parse_args()
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING
    for task in args.tasks:
        for preset in args.presets:
            t0 = time.perf_counter()
            digest = episode_hash(task, preset, args.init_state, args.steps, args.env_kwargs)
            print(f"episode_hash {task} {preset} init{args.init_state} steps{args.steps}: {digest} "
                  f"({time.perf_counter() - t0:.1f} s)", flush=True)


if __name__ == "__main__":
    main()
