"""Robot kinematics speed on the built-in arm: IK solves per second (single, batch of 256), FK, controller
step, and FK + Gaussian update for 100,000 robot Gaussians.

Prints `name value unit` lines (median of repeated runs, after a warm-up).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from twinbench.robot.builtin import load_builtin_arm
from twinbench.robot.controller import RobotController
from twinbench.robot.gaussians import sample_robot_scan
from twinbench.robot.ik import random_configurations, solve_ik
from twinbench.transforms import matrix_to_quat


def _median_time(fn, repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args()
    arm = load_builtin_arm("gripper")
    rng = np.random.default_rng(0)
    # Targets: FK of random in-limit configurations; solved from a warm start 0.3 rad away (per joint,
    # random sign), the situation of a controller or of a policy's next chunk.
    q_true = random_configurations(arm, 256, rng)
    targets = arm.ee_pose(q_true)
    warm = arm.clip_q(q_true + rng.choice([-0.3, 0.3], size=q_true.shape))

    def single():
        for i in range(32):
            solve_ik(arm, targets[i], warm[i])

    t = _median_time(single, args.repeats)
    print(f"ik_single_solves_per_s {32 / t:.1f} solves/s")
    t = _median_time(lambda: solve_ik(arm, targets, warm), args.repeats)
    print(f"ik_batch256_solves_per_s {256 / t:.1f} solves/s")
    cold = np.broadcast_to(arm.home_q, q_true.shape)
    t = _median_time(lambda: solve_ik(arm, targets, cold), args.repeats)
    print(f"ik_batch256_from_home_solves_per_s {256 / t:.1f} solves/s")
    t = _median_time(lambda: arm.fk(q_true), args.repeats)
    print(f"fk_batch256_all_links {t * 1e3:.3f} ms")

    ctrl = RobotController(arm)
    goal = arm.ee_pose(arm.home_q + np.r_[0.5, 0.3, 0.0, 0.4, 0.2, -0.3, 0.5, 0.0])
    action = np.concatenate([goal[:3, 3], matrix_to_quat(goal[:3, :3]), [1.0]])

    def control():
        ctrl.reset()
        for _ in range(30):
            ctrl.step(action, finger_forces=(0.0, 0.0))

    t = _median_time(control, args.repeats)
    print(f"controller_step {t / 30 * 1e3:.3f} ms")

    scan = sample_robot_scan(arm, n_gaussians=100_000, seed=0)
    qs = random_configurations(arm, 16, rng)
    it = iter(range(10**9))

    def pose():
        scan.posed(qs[next(it) % 16])

    t = _median_time(pose, max(args.repeats, 20))
    print(f"fk_gaussian_update_100k {t * 1e3:.3f} ms")


if __name__ == "__main__":
    main()
