"""CUDA against the CPU reference, whole episodes: the scripted expert drives each task's env on `cpu` and on
`cuda:0` with the CPU run's actions replayed on CUDA (so both see the same commands), and the script prints,
per task and preset, how far the CUDA run drifts from the CPU one: object particles (max and mean distance
per step), the robot's joint positions, the images (mean and max absolute difference in levels, share of
pixels that differ by more than 8 levels) and whether the task's success flags agree step by step; then env
steps per second on both devices. Skips CUDA (and says so) without a GPU.

    python benchmarks/cuda_check.py                       # every task, preset fast, 40 steps
    python benchmarks/cuda_check.py --tasks push-t --presets fast reference --steps 80

GPU code contracts multiply-adds differently from the CPU build, so the trajectories are not bitwise equal;
contact and friction make small differences grow. The figures say by how much; BENCHMARKS.md keeps them.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def run(task: str, preset: str, device: str, steps: int, init_state: int, actions=None):
    """Per step: object particles, joint positions, front images, success flag; and the actions taken."""
    from twinbench.tasks import get_task

    spec = get_task(task)
    env = spec.make_env(preset=preset, device=device, environment_state=True)
    obs, info = env.reset(seed=0, options={"init_state": init_state})
    expert = None
    if actions is None:
        expert = spec.make_expert(env)
        expert.reset()
    twin, state = env.unwrapped.twin, env.unwrapped.state
    rec = {"particles": [], "joints": [], "pixels": [], "success": [], "actions": [], "step_s": []}
    for k in range(steps):
        action = expert.select_action(obs) if expert is not None else actions[k]
        t0 = time.perf_counter()
        obs, _, _, _, info = env.step(action)
        rec["step_s"].append(time.perf_counter() - t0)
        rec["actions"].append(np.asarray(action, np.float32).copy())
        rec["particles"].append(np.concatenate([twin.particles(state, n) for n in twin.object_names]))
        rec["joints"].append(np.asarray(obs["joint_position"], np.float64))
        rec["pixels"].append(np.stack([obs["pixels"][c] for c in sorted(obs["pixels"])]).astype(np.int16))
        rec["success"].append(bool(info["is_success"]))
    env.close()
    return rec


def compare(cpu: dict, gpu: dict) -> dict:
    d = [np.linalg.norm(a - b, axis=1) for a, b in zip(cpu["particles"], gpu["particles"], strict=True)]
    px = [np.abs(a - b) for a, b in zip(cpu["pixels"], gpu["pixels"], strict=True)]
    joints = max(np.abs(a - b).max() for a, b in zip(cpu["joints"], gpu["joints"], strict=True))
    return {
        "particles_max_mm": 1e3 * max(x.max() for x in d),
        "particles_mean_mm": 1e3 * float(np.mean([x.mean() for x in d])),
        "particles_max_mm_first10": 1e3 * max(x.max() for x in d[:10]),
        "joints_max_rad": float(joints),
        "pixels_mean_levels": float(np.mean([p.mean() for p in px])),
        "pixels_max_levels": int(max(p.max() for p in px)),
        "pixels_over8_share": float(np.mean([(p.max(axis=-1) > 8).mean() for p in px])),
        "success_agree": float(np.mean(np.equal(cpu["success"], gpu["success"]))),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--tasks", nargs="+", default=["push-t", "rope-routing", "toy-packing"])
    p.add_argument("--presets", nargs="+", default=["fast"])
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--init-state", type=int, default=1)
    args = p.parse_args()
    import warp as wp

    from twinbench._runtime import quiet_warp

    quiet_warp()
    has_cuda = wp.get_cuda_device_count() > 0
    if has_cuda:
        from twinbench.gaussians.render import gsplat_available

        # render_batch's "auto" backend: a twin on CUDA renders with gsplat whenever the extra is installed
        print(f"cuda device: {wp.get_device('cuda:0').name}; renderer: "
              f"{'gsplat' if gsplat_available() else 'warp'}")
    else:
        print("no CUDA device: CPU figures only")
    for task in args.tasks:
        for preset in args.presets:
            tag = f"{task}_{preset}"
            cpu = run(task, preset, "cpu", args.steps, args.init_state)
            print(f"{tag}_cpu_env_steps_per_s {1.0 / np.median(cpu['step_s'][3:]):.2f} steps/s", flush=True)
            if not has_cuda:
                continue
            gpu = run(task, preset, "cuda:0", args.steps, args.init_state, actions=cpu["actions"])
            print(f"{tag}_cuda_env_steps_per_s {1.0 / np.median(gpu['step_s'][3:]):.2f} steps/s")
            for key, value in compare(cpu, gpu).items():
                print(f"{tag}_cuda_vs_cpu_{key} {value:.4g}", flush=True)


if __name__ == "__main__":
    main()
