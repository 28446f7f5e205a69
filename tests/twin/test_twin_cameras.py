import numpy as np
import pytest

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.render import render
from twinbench.scene.assets import backdrop_gaussians, table_gaussians
from twinbench.scene.cameras import (
    FRONT_INTRINSICS,
    SENSOR_SIZE,
    CameraSpec,
    look_at_pose,
    policy_intrinsics,
)


def _project(cam: Camera, pts: np.ndarray) -> np.ndarray:
    p = pts @ cam.world_to_cam[:3, :3].T + cam.world_to_cam[:3, 3]
    return np.c_[cam.fx * p[:, 0] / p[:, 2] + cam.cx, cam.fy * p[:, 1] / p[:, 2] + cam.cy]


def test_policy_intrinsics_equal_crop_then_resize():
    # 240x240 from 848x480: central 480x480 square (x0 = 184), then scale 0.5.
    fx, fy, cx, cy = policy_intrinsics(FRONT_INTRINSICS, SENSOR_SIZE, (240, 240))
    assert (fx, fy, cx, cy) == pytest.approx((427.29 / 2, 426.79 / 2, (430.0 - 184) / 2, 242.81 / 2))
    # 120x212 has the sensor's aspect ratio: a plain 1/4 resize.
    assert policy_intrinsics(FRONT_INTRINSICS, SENSOR_SIZE, (120, 212)) == pytest.approx(
        tuple(v / 4 for v in FRONT_INTRINSICS)
    )
    spec = CameraSpec("front", FRONT_INTRINSICS, look_at_pose((1.0, -0.4, 0.5), (0.45, 0, 0)))
    full, small = spec.camera((480, 848)), spec.camera((240, 240))
    pts = np.random.default_rng(0).uniform([0.3, -0.2, 0.0], [0.6, 0.2, 0.1], (50, 3))
    expected = (_project(full, pts) - [184.0, 0.0]) * 0.5
    np.testing.assert_allclose(_project(small, pts), expected, atol=1e-9)


def test_rendering_at_policy_intrinsics_matches_cropped_downsampled_sensor_image():
    cloud = GaussianCloud.concatenate([table_gaussians(spacing=0.01), backdrop_gaussians(spacing=0.02)])
    spec = CameraSpec("front", FRONT_INTRINSICS, look_at_pose((1.0, -0.4, 0.5), (0.45, 0, 0)))
    full = render(cloud, spec.camera((480, 848))).rgb
    small = render(cloud, spec.camera((240, 240))).rgb
    crop = full[:, 184:664]
    box = crop.reshape(240, 2, 240, 2, 3).mean(axis=(1, 3))
    assert np.abs(small - box).mean() < 0.02


def test_wrist_camera_moves_with_its_link():
    offset = look_at_pose((0.0, -0.1, 0.0), (0.0, 0.0, 0.2), up=(1.0, 0.0, 0.0))
    spec = CameraSpec("wrist", FRONT_INTRINSICS, offset, mount_link="link7")
    link = np.eye(4)
    link[:3, :3] = [[0, -1, 0], [1, 0, 0], [0, 0, 1]]
    link[:3, 3] = [0.4, 0.1, 0.3]
    np.testing.assert_allclose(spec.camera((240, 240), link).cam_to_world, link @ offset, atol=1e-12)
    with pytest.raises(ValueError, match="link_pose"):
        spec.camera((240, 240))
