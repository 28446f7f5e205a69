"""Construction tools on CPU: robot registration of a 200k-Gaussian scan (FPFH + RANSAC + ICP + labels),
the IRLS colour-map fit (two 848x480 image pairs) plus its application to the 200k Gaussians, and camera
refinement of the push-T cell's front camera (240x240, the study's calibration error) on a recoloured,
noisy image of the cell's scene.

Prints `name value unit` lines; run as `python benchmarks/construction.py`.
"""

from __future__ import annotations

import time

import numpy as np

from twinbench._runtime import quiet_warp
from twinbench.construct.align_color import fit_color_map
from twinbench.construct.align_robot import RegistrationParams, gaussian_normals, register_robot
from twinbench.gaussians.colormap import apply_color_map, identity_color_map, map_colors
from twinbench.robot.builtin import load_builtin_arm
from twinbench.robot.gaussians import sample_robot_scan
from twinbench.transforms import rotation_angle, rotvec_to_matrix

N = 200_000


def main() -> None:
    quiet_warp()
    rng = np.random.default_rng(0)
    model = load_builtin_arm("gripper")
    q = model.set_gripper(model.home_q.copy(), 0.5)
    n_robot = int(0.8 * N)
    world = sample_robot_scan(model, n_gaussians=n_robot, seed=1).posed(q)
    true = np.eye(4)
    true[:3, :3] = 1.1 * rotvec_to_matrix(np.radians(40.0) * np.array([0.6, 0.0, 0.8]))
    true[:3, 3] = [0.2, -0.1, 0.15]
    pts = world.means.astype(np.float64) @ true[:3, :3].T + true[:3, 3] + rng.normal(0, 0.002, (n_robot, 3))
    lo, hi = pts.min(0) - 0.1, pts.max(0) + 0.1
    scan = np.concatenate([pts, rng.uniform(lo, hi, (N - n_robot, 3))])
    normals = gaussian_normals(world) @ true[:3, :3].T / 1.1
    normals = np.concatenate([normals, np.full((N - n_robot, 3), np.nan)])
    t0 = time.perf_counter()
    res = register_robot(scan, model, q, RegistrationParams(estimate_scale=True), scan_normals=normals)
    total = time.perf_counter() - t0
    err = res.transform @ true
    s = np.cbrt(np.linalg.det(err[:3, :3]))
    print(f"registration_200k_total {total:.2f} s")
    for k, v in res.timings.items():
        print(f"registration_200k_{k} {v:.2f} s")
    rot_err = np.degrees(rotation_angle(err[:3, :3] / s, np.eye(3)))
    print(f"registration_200k_rotation_error {rot_err:.4f} deg")
    print(f"registration_200k_translation_error {np.linalg.norm(err[:3, 3]) * 1e3:.3f} mm")
    acc = (res.labels[:n_robot] == world_labels(model, n_robot)).mean()
    print(f"registration_200k_label_accuracy {acc:.4f} fraction (all sampled surface, hidden parts included)")

    a = identity_color_map(2)
    a[:, 0] = [0.03, -0.02, 0.01]
    a[:, 4:] = rng.uniform(-0.05, 0.05, (3, 6))
    src = rng.uniform(0, 1, (2 * 848 * 480, 3))
    dst = map_colors(src, a) + rng.normal(0, 0.01, src.shape)
    bad = rng.random(len(src)) < 0.1
    dst[bad] = rng.uniform(0, 1, (bad.sum(), 3))
    t0 = time.perf_counter()
    fit = fit_color_map(src, dst, degree=2, iterations=50)
    t_fit = time.perf_counter() - t0
    t0 = time.perf_counter()
    apply_color_map(world, fit.coeffs, 2)
    t_apply = time.perf_counter() - t0
    print(f"color_fit_2x848x480_irls {t_fit:.2f} s ({fit.iterations} iterations)")
    print(f"color_apply_{n_robot // 1000}k_gaussians {t_apply * 1e3:.1f} ms")
    refine_benchmark(rng)


def refine_benchmark(rng) -> None:
    import dataclasses

    from twinbench.construct.refine_camera import image_shift, refine_camera
    from twinbench.gaussians.cloud import GaussianCloud
    from twinbench.gaussians.render import render
    from twinbench.study.real import perturbed_pose
    from twinbench.twin import build_twin
    from twinbench.twin.cells import push_t_cell

    cell = push_t_cell("fast")
    twin, _ = build_twin(cell)
    block = cell.objects[0]
    scene = GaussianCloud.concatenate([twin.robot_gaussians.posed(twin.robot.home_q),
                                       block.gaussians.transform(block.rest_pose), cell.background])
    true = cell.camera("front")
    rgb = np.asarray(render(scene, [true.view()])[0].rgb, np.float64)
    real = np.clip((rgb @ np.array([[0.9, 0.08, 0.0], [0.05, 0.85, 0.1], [0.0, 0.1, 0.95]]).T + 0.03) ** 0.8
                   + rng.normal(0.0, 0.01, rgb.shape), 0.0, 1.0)
    k = np.asarray(true.intrinsics) * (1.0 + rng.normal(0.0, 0.005, 4))
    calib = dataclasses.replace(true, pose=perturbed_pose(true.pose, rng, 0.003, 0.3), intrinsics=tuple(k))
    t0 = time.perf_counter()
    fit = refine_camera(scene, calib, real)
    took = time.perf_counter() - t0
    before, after = (float(np.median(image_shift(c, true, scene.means))) for c in (calib, fit.camera))
    print(f"refine_camera_240px_{len(scene) // 1000}k_gaussians {took:.1f} s ({fit.evaluations} renders)")
    print(f"refine_camera_image_error {before:.2f} -> {after:.3f} px (median)")


def world_labels(model, n_robot: int) -> np.ndarray:
    return sample_robot_scan(model, n_gaussians=n_robot, seed=1).link_index


if __name__ == "__main__":
    main()
