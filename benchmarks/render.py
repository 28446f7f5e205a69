"""Render and skinning speed: 200k surface-like Gaussians seen from ~1 m; LBS of 100k Gaussians; a twin's
cameras with the render cache on and off.

Twin (`--twin-steps`, 0 skips it): the `fast` push-T twin (one world) stepped by its scripted expert; per
step, both 240x240 cameras (`Twin.render`) and the front camera alone, the render cache
(`Twin.render_cache`) on in even steps and off in odd ones (A/B in one run, the same states); the front
camera does not move, so with the cache only the robot's and the T's Gaussians are projected. Each cached
image is checked equal to the uncached one of the same state.

Prints `name value unit` lines (median of repeated runs, after a warm-up). `*_cpu_time` lines give the
process CPU time per frame summed over threads; wall time below it means the threads ran in parallel,
wall time above it means other processes were competing for the cores.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import warp as wp

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.primitives import quat_z_to
from twinbench.gaussians.render import RenderCache, gsplat_available, render, render_batch
from twinbench.gaussians.skinning import LBSSkinner, bind


def surface_scene(n: int = 200_000, seed: int = 0) -> GaussianCloud:
    """Thin discs (3-10 mm, 0.5 mm thick) tangent to a table plane, a back wall and three spheres."""
    rng = np.random.default_rng(seed)
    parts = []
    normals = []
    n_plane = n // 4
    table = np.c_[rng.uniform(-0.6, 0.6, n_plane), rng.uniform(-0.4, 0.6, n_plane), np.zeros(n_plane)]
    parts.append(table)
    normals.append(np.tile([0, 0, 1.0], (n_plane, 1)))
    wall = np.c_[rng.uniform(-0.6, 0.6, n_plane), np.full(n_plane, 0.6), rng.uniform(0, 0.6, n_plane)]
    parts.append(wall)
    normals.append(np.tile([0, -1.0, 0], (n_plane, 1)))
    rest = n - 2 * n_plane
    for i, (c, r) in enumerate(
        [((-0.2, 0.1, 0.1), 0.1), ((0.15, 0.2, 0.08), 0.08), ((0.0, -0.1, 0.05), 0.05)]
    ):
        m = rest // 3 if i < 2 else rest - 2 * (rest // 3)
        d = rng.normal(size=(m, 3))
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        parts.append(np.asarray(c) + r * d)
        normals.append(d)
    means = np.concatenate(parts)
    nrm = np.concatenate(normals)
    quats = quat_z_to(nrm)  # disc normal (local z) -> surface normal
    log_scales = np.c_[np.log(rng.uniform(0.003, 0.01, (n, 2))), np.full(n, np.log(0.0005))]
    sh = rng.normal(scale=0.5, size=(n, 1, 3))
    return GaussianCloud(means, quats, log_scales, np.full(n, 3.0), sh)


def median_ms(fn, repeats: int) -> float:
    """Median wall-clock ms after one warm-up call; also keeps the median process CPU ms in LAST_CPU_MS
    (CPU time summed over threads: tells contention from other processes apart from our own cost)."""
    global LAST_CPU_MS
    fn()
    times, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        times.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    LAST_CPU_MS = 1000.0 * float(np.median(cpu))
    return 1000.0 * float(np.median(times))


LAST_CPU_MS = 0.0


def bench_twin(device: str, steps: int, warmup: int = 4) -> None:
    from twinbench.env import TwinEnv
    from twinbench.evaluation.rollout import policy_observation
    from twinbench.tasks import get_task

    env = TwinEnv("push-t", preset="fast", device=device)
    obs, info = env.reset(seed=0, options={"init_state": 0})
    expert = get_task("push-t").make_expert(env)
    twin, state = env.twin, env.state
    cache = twin.render_cache or RenderCache()  # on CUDA twins render without it by default
    both: dict = {True: [], False: []}
    front: dict = {True: [], False: []}
    cpu: dict = {True: [], False: []}  # process CPU time of both cameras (all threads)
    for k in range(warmup + 2 * steps):
        twin.render_cache = None  # the env's own render: not asking for the wrist camera's pose twice
        obs, _, _, _, info = env.step(expert.select_action(policy_observation(expert, obs, info)))
        for on in (k % 2 == 0, k % 2 != 0):  # this step's A first, then B (the other order next step)
            twin.render_cache = cache if on else None
            t0, c0 = time.perf_counter(), time.process_time()
            images = twin.render(state)
            t1, c1 = time.perf_counter(), time.process_time()
            twin.render(state, ["front"])
            t2 = time.perf_counter()
            if k >= warmup:
                both[on].append(t1 - t0)
                front[on].append(t2 - t1)
                cpu[on].append(c1 - c0)
            if on:
                cached = images
            else:
                full = images
        for name in full:
            if not np.array_equal(cached[name].rgb, full[name].rgb):
                raise AssertionError(f"render cache: {name} differs from the full render at step {k}")
    twin.render_cache = cache
    tag = f"twin_pusht_fast_{device.replace(':', '')}"
    for label, times in (("2cams_240", both), ("front_240", front), ("2cams_240_cpu_time", cpu)):
        print(f"{tag}_{label}_ms {1e3 * np.median(times[True]):.1f} ms")
        print(f"{tag}_{label}_ms_cache_off {1e3 * np.median(times[False]):.1f} ms")
    print(f"{tag}_cache_builds_hits_misses {cache.builds}/{cache.hits}/{cache.misses} count")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--twin-steps", type=int, default=20, help="steps of the twin A/B (0: skip it)")
    ap.add_argument("--only-twin", action="store_true", help="only the twin A/B")
    args = ap.parse_args()
    wp.init()
    devices = ["cpu"] + [f"cuda:{i}" for i in range(wp.get_cuda_device_count())]
    if args.twin_steps:
        from twinbench._runtime import quiet_warp

        quiet_warp()
        for device in devices:
            bench_twin(device, args.twin_steps)
    if args.only_twin:
        return
    cloud = surface_scene()
    eye, target = (0.0, -0.85, 0.55), (0.0, 0.15, 0.1)
    cams = {
        "848x480": Camera.look_at(
            eye, target, fx=427.29, fy=426.79, cx=430.0, cy=242.81, width=848, height=480
        ),
        "240x240": Camera.look_at(eye, target, fx=220.0, width=240, height=240),
    }
    for device in devices:
        g = cloud.to_device(device)
        backends = ["warp"] + (["gsplat"] if device != "cpu" and gsplat_available() else [])
        for backend in backends:
            if backend == "warp":
                pair = [
                    cams["848x480"],
                    Camera.look_at(
                        (0.3, -0.5, 0.35),
                        (0.0, 0.1, 0.05),
                        fx=433.26,
                        cx=425.70,
                        cy=244.70,
                        width=848,
                        height=480,
                    ),
                ]
                ms = median_ms(
                    lambda src=g, d=device, pair=pair: render(src, pair, backend="warp", device=d),
                    args.repeats,
                )
                print(f"render_{backend}_{device.replace(':', '')}_2cams_848x480_200k {ms:.1f} ms")
                if device == "cpu":
                    print(f"render_{backend}_cpu_2cams_848x480_200k_cpu_time {LAST_CPU_MS:.1f} ms")
            for name, cam in cams.items():
                ms = median_ms(
                    lambda src=g, cam=cam, b=backend, d=device: render(src, cam, backend=b, device=d),
                    args.repeats,
                )
                print(f"render_{backend}_{device.replace(':', '')}_{name}_200k {ms:.1f} ms")
                if device == "cpu":
                    print(f"render_{backend}_cpu_{name}_200k_cpu_time {LAST_CPU_MS:.1f} ms")
    # a close-up (a wrist camera 15 cm over the table) moving every frame: full renders of the whole scene
    # against the scene in spatial order as a SplitGaussians' static part with a RenderCache (its chunks
    # culled 32 Gaussians at a time; the camera moves, so no other work is kept)
    from twinbench.gaussians.cloud import SplitGaussians

    for device in devices:
        if device != "cpu":
            continue  # chunk culling is the CPU projection's (on CUDA a thread per Gaussian)
        sorted_cloud, tool_cloud = cloud.spatially_sorted(), surface_scene(500, seed=1)
        static, tool = sorted_cloud.to_device(device), tool_cloud.to_device(device)
        whole = GaussianCloud.concatenate([sorted_cloud, tool_cloud]).to_device(device)
        cache, frames = RenderCache(), iter(range(10**6))

        def closeup(frames=frames) -> Camera:
            dx = 1e-4 * next(frames)  # a new pose every frame
            return Camera.look_at((0.05 + dx, -0.1, 0.15), (0.05 + dx, -0.05, 0.0), fx=220.0, width=240,
                                  height=240)

        split = SplitGaussians(static, tool)
        for label, fn in (
            ("whole", lambda whole=whole, d=device: render(whole, closeup(), backend="warp", device=d)),
            ("chunks", lambda split=split, d=device, c=cache: render_batch(
                [(split, closeup())], backend="warp", device=d, cache=c)),
        ):
            print(f"render_warp_cpu_closeup_240x240_200k_{label} {median_ms(fn, args.repeats):.1f} ms")
    # LBS: 100k Gaussians bound to 3,000 particles (a wavy sheet), one frame of motion
    rng = np.random.default_rng(1)
    particles = np.c_[rng.uniform(-0.2, 0.2, (3000, 2)), rng.uniform(0, 0.02, 3000)]
    gauss = particles[rng.integers(0, 3000, 100_000)] + rng.normal(scale=0.005, size=(100_000, 3))
    quats = np.tile([1.0, 0, 0, 0], (100_000, 1))
    moved = particles + np.c_[np.zeros((3000, 2)), 0.05 * np.sin(10 * particles[:, :1])]
    for device in devices:
        # median after a warm-up call (the first one imports scipy.spatial)
        bind_ms = median_ms(lambda device=device: bind(gauss, particles, device=device), 3)
        binding = bind(gauss, particles, device=device)
        skinner = LBSSkinner(binding, gauss, quats, device=device)
        p_dev = wp.array(moved, dtype=wp.vec3, device=device)

        def step(skinner=skinner, p_dev=p_dev, device=device):
            skinner.update(p_dev)
            wp.synchronize_device(device)

        print(f"lbs_bind_{device.replace(':', '')}_100k_3k {bind_ms:.1f} ms")
        print(f"lbs_update_{device.replace(':', '')}_100k_3k {median_ms(step, args.repeats):.2f} ms")


if __name__ == "__main__":
    main()
