"""GaussianCloud operations, SH basis/rotation and Camera, with known answers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.render import render
from twinbench.gaussians.sh import eval_sh_colour, rotate_sh, sh_basis
from twinbench.transforms import matrix_to_quat, quat_multiply, quat_to_matrix


def test_sh_basis_is_orthonormal_on_the_sphere():
    # Gauss-Legendre in cos(theta) x uniform phi integrates these polynomials (degree <= 6) exactly
    x, w = np.polynomial.legendre.leggauss(8)
    phi = np.arange(16) * 2 * np.pi / 16
    ct, ph = np.meshgrid(x, phi, indexing="ij")
    st = np.sqrt(1 - ct**2)
    dirs = np.stack([st * np.cos(ph), st * np.sin(ph), ct], -1).reshape(-1, 3)
    weights = (w[:, None] * np.full(16, 2 * np.pi / 16)).reshape(-1)
    basis = sh_basis(dirs, 3)
    gram = basis.T @ (basis * weights[:, None])
    np.testing.assert_allclose(gram, np.eye(16), atol=1e-12)


def test_rotate_sh_rotates_the_colour_field(make_cloud):
    cloud = make_cloud(50, degree=3, seed=1)
    rot = Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix()
    rotated = rotate_sh(cloud.sh, rot)
    d = np.random.default_rng(2).normal(size=(50, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    # f'(R d) = f(d)
    np.testing.assert_allclose(eval_sh_colour(rotated, d @ rot.T), eval_sh_colour(cloud.sh, d), atol=1e-5)
    np.testing.assert_array_equal(rotated[:, 0], cloud.sh[:, 0])


def test_quaternion_helpers_match_scipy():
    rots = Rotation.random(20, random_state=0)
    q_xyzw = rots.as_quat()
    q = np.c_[q_xyzw[:, 3], q_xyzw[:, :3]]
    np.testing.assert_allclose(quat_to_matrix(q), rots.as_matrix(), atol=1e-12)
    for i in range(20):
        qi = matrix_to_quat(rots[i].as_matrix())
        assert abs(abs(np.dot(qi, q[i])) - 1) < 1e-12
    prod = quat_multiply(q[:10], q[10:])
    np.testing.assert_allclose(quat_to_matrix(prod), (rots[:10] * rots[10:]).as_matrix(), atol=1e-12)


def test_concatenate_pads_sh_and_subset(make_cloud):
    a = make_cloud(5, degree=0, seed=1)
    b = make_cloud(7, degree=2, seed=2)
    c = GaussianCloud.concatenate([a, b])
    assert len(c) == 12 and c.sh_degree == 2
    np.testing.assert_array_equal(c.sh[:5, 0], a.sh[:, 0])
    assert np.all(c.sh[:5, 1:] == 0)
    np.testing.assert_array_equal(c.subset(slice(5, None)).sh, b.sh)
    mask = np.zeros(12, bool)
    mask[[1, 6]] = True
    np.testing.assert_array_equal(c.subset(mask).means, c.means[[1, 6]])
    np.testing.assert_array_equal(c.subset([6, 1]).means, c.means[[6, 1]])
    with pytest.raises(ValueError, match="mask"):
        c.subset(np.ones(3, bool))
    with pytest.raises(ValueError, match="empty"):
        GaussianCloud.concatenate([])


def test_crop_oriented_box_known_answer():
    # box rotated 45 deg about z, centred at (1, 0, 0), half extents (0.5, 0.1, 0.2)
    rot = Rotation.from_euler("z", 45, degrees=True).as_matrix()
    d = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0])
    pts = np.array(
        [
            [1, 0, 0],  # centre: inside
            [1, 0, 0] + 0.45 * d,  # along the long axis: inside
            [1.45, 0, 0],  # along world x, 0.45 m: |local y| = 0.32 > 0.1: outside
            [1, 0, 0.25],  # above: outside
            [1, 0, 0] - 0.49 * d + [0, 0, 0.19],  # inside
        ]
    )
    n = len(pts)
    cloud = GaussianCloud(
        pts, np.tile([1.0, 0, 0, 0], (n, 1)), np.zeros((n, 3)), np.zeros(n), np.zeros((n, 1, 3))
    )
    np.testing.assert_array_equal(cloud.box_mask((1, 0, 0), rot, (0.5, 0.1, 0.2)), [1, 1, 0, 0, 1])
    assert len(cloud.crop((1, 0, 0), rot, (0.5, 0.1, 0.2))) == 3
    np.testing.assert_allclose(
        cloud.crop((1, 0, 0), rot, (0.5, 0.1, 0.2), invert=True).means, pts[[2, 3]], atol=1e-7
    )


def test_downsample_keeps_largest_opacity_times_volume():
    n = 6
    log_scales = np.log(np.array([[0.01] * 3, [0.02] * 3, [0.01] * 3, [0.03] * 3, [0.01] * 3, [0.02] * 3]))
    opac = np.array([0.9, 0.1, 0.5, 0.05, 0.99, 0.5])
    # opacity * volume (1e-6 units): 0.9, 0.8, 0.5, 1.35, 0.99, 4.0 -> keep 5, 3, 4 (in original order)
    cloud = GaussianCloud(
        np.arange(n * 3).reshape(n, 3),
        np.tile([1.0, 0, 0, 0], (n, 1)),
        log_scales,
        np.log(opac / (1 - opac)),
        np.zeros((n, 1, 3)),
    )
    out = cloud.downsample(3)
    np.testing.assert_array_equal(out.means[:, 0], cloud.means[[3, 4, 5], 0])
    assert len(cloud.downsample(10)) == n
    with pytest.raises(ValueError):
        cloud.downsample(-1)


def test_transform_moves_means_quats_scales(make_cloud):
    cloud = make_cloud(30, degree=0, seed=4)
    rot = Rotation.from_rotvec([0.2, 0.4, -0.3]).as_matrix()
    t = np.eye(4)
    t[:3, :3] = 2.0 * rot
    t[:3, 3] = [0.1, -0.2, 0.3]
    out = cloud.transform(t)
    np.testing.assert_allclose(out.means, 2.0 * cloud.means @ rot.T + t[:3, 3], atol=1e-6)
    np.testing.assert_allclose(quat_to_matrix(out.quats), rot @ quat_to_matrix(cloud.quats), atol=1e-6)
    np.testing.assert_allclose(out.log_scales, cloud.log_scales + np.log(2.0), atol=1e-6)
    with pytest.raises(ValueError, match="rotation"):
        cloud.transform(np.diag([1.0, 2.0, 1.0, 1.0]))
    with pytest.raises(ValueError, match="reflection"):
        cloud.transform(np.diag([1.0, 1.0, -1.0, 1.0]))


def test_rendering_is_invariant_under_moving_cloud_and_camera_together(make_cloud):
    """transform() with SH rotation: moving scene and camera by one rigid motion gives the same image."""
    cloud = make_cloud(150, degree=3, anisotropic=True, seed=8)
    cam = Camera.look_at((1.0, 0.3, 0.4), (0, 0, 0), fx=60, width=64, height=48)
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_rotvec([0.5, -0.9, 1.3]).as_matrix()
    motion[:3, 3] = [0.3, -1.0, 2.0]
    moved_cam = Camera(cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height, motion @ cam.cam_to_world)
    a = render(cloud, cam)
    b = render(cloud.transform(motion), moved_cam)
    assert np.abs(a.rgb - b.rgb).max() < 2e-3
    dc_only = render(cloud.transform(motion, sh_mode="dc_only"), moved_cam)
    assert np.abs(a.rgb - dc_only.rgb).max() > 0.02, "degree-3 colours must change without SH rotation"


def test_device_arrays(make_cloud):
    cloud = make_cloud(10, degree=1)
    unit = cloud.quats.copy()
    cloud.quats *= 3.0  # unnormalised on the host
    cloud.quats[0] = 0.0  # a zero quaternion becomes the identity
    dev = cloud.to_device("cpu")
    assert len(dev) == 10 and dev.sh.shape == (10, 4)
    np.testing.assert_allclose(np.linalg.norm(dev.quats.numpy(), axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(dev.quats.numpy()[1:], unit[1:], atol=1e-6)
    np.testing.assert_array_equal(dev.quats.numpy()[0], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_array_equal(dev.means.numpy(), cloud.means)
    np.testing.assert_array_equal(dev.sh.numpy(), cloud.sh)
    np.testing.assert_allclose(dev.scales.numpy(), np.exp(cloud.log_scales), rtol=1e-6)
    np.testing.assert_allclose(dev.opacities.numpy(), 1 / (1 + np.exp(-cloud.logit_opacities)), rtol=1e-6)


def test_camera_look_at_projection_and_inverse():
    cam = Camera.look_at((2.0, -1.0, 1.5), (0.2, 0.3, 0.1), fx=500, width=640, height=480)
    w2c = cam.world_to_cam
    np.testing.assert_allclose(w2c @ cam.cam_to_world, np.eye(4), atol=1e-12)
    p = w2c @ [0.2, 0.3, 0.1, 1.0]
    assert p[0] == pytest.approx(0, abs=1e-12) and p[1] == pytest.approx(0, abs=1e-12) and p[2] > 0
    # a point above the target (world +z) appears higher in the image (smaller v)
    q = w2c @ [0.2, 0.3, 0.3, 1.0]
    assert cam.fy * q[1] / q[2] + cam.cy < cam.cy
    np.testing.assert_allclose(cam.K, [[500, 0, 320], [0, 500, 240], [0, 0, 1]])
    with pytest.raises(ValueError, match="parallel"):
        Camera.look_at((0, 0, 1), (0, 0, 0), fx=100, width=10, height=10)
    with pytest.raises(ValueError, match="rotation"):
        Camera(100, 100, 5, 5, 10, 10, np.diag([1.0, 1.0, -1.0, 1.0]))
    with pytest.raises(ValueError, match="fx"):
        Camera(0, 100, 5, 5, 10, 10)


def test_spatially_sorted_is_a_permutation_that_groups_neighbours(make_cloud):
    """Morton order: the same Gaussians (every field moved together), and runs of 32 consecutive ones
    about as tight in space as a grid cell of 32 (0.8 of a 2 m box's 3.3 in a random order)."""
    cloud = make_cloud(4096, degree=1, seed=3, spread=1.0)
    out = cloud.spatially_sorted()
    order = np.lexsort(cloud.means.T)
    back = np.lexsort(out.means.T)
    for field in ("means", "quats", "log_scales", "logit_opacities", "sh"):
        np.testing.assert_array_equal(getattr(out, field)[back], getattr(cloud, field)[order])

    def run_extent(c):
        m = c.means.reshape(-1, 32, 3)
        return np.median(np.linalg.norm(m.max(axis=1) - m.min(axis=1), axis=1))

    assert run_extent(out) < 0.3 * run_extent(cloud)
