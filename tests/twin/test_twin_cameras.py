"""Twin cameras: crop + resize folded into the intrinsics, policy-resolution rendering, wrist mounting."""

import numpy as np
import pytest

from twinbench.gaussians.camera import Camera, look_at_pose
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.render import render
from twinbench.twin.assets import backdrop_gaussians, table_gaussians
from twinbench.twin.cells import FRONT_INTRINSICS
from twinbench.twin.spec import CameraSpec

POSE = look_at_pose((1.0, -0.4, 0.5), (0.45, 0, 0))


def _project(cam: Camera, pts: np.ndarray) -> np.ndarray:
    p = pts @ cam.world_to_cam[:3, :3].T + cam.world_to_cam[:3, 3]
    return np.c_[cam.fx * p[:, 0] / p[:, 2] + cam.cx, cam.fy * p[:, 1] / p[:, 2] + cam.cy]


def _camera(spec: CameraSpec, link_pose=None) -> Camera:
    fx, fy, cx, cy = spec.output_intrinsics()
    pose = spec.pose if link_pose is None else link_pose @ spec.pose
    return Camera(fx, fy, cx, cy, spec.output_hw[1], spec.output_hw[0], pose)


def test_output_intrinsics_equal_crop_then_resize():
    # 240x240 from 848x480: central 480x480 square (x0 = 184), then scale 0.5.
    spec = CameraSpec("front", FRONT_INTRINSICS, POSE, output_hw=(240, 240))
    assert spec.crop_box() == pytest.approx((184.0, 0.0, 480.0, 480.0))
    assert spec.output_intrinsics() == pytest.approx((427.29 / 2, 426.79 / 2, (430.0 - 184) / 2, 242.81 / 2))
    # 120x212 has the sensor's aspect ratio: a plain 1/4 resize.
    quarter = CameraSpec("front", FRONT_INTRINSICS, POSE, output_hw=(120, 212))
    assert quarter.output_intrinsics() == pytest.approx(tuple(v / 4 for v in FRONT_INTRINSICS))
    # an explicit crop box: the right 400x300 region of the sensor at 200x150
    boxed = CameraSpec("front", FRONT_INTRINSICS, POSE, crop=(448, 100, 400, 300), output_hw=(150, 200))
    full = CameraSpec("front", FRONT_INTRINSICS, POSE, crop=(0, 0, 848, 480), output_hw=(480, 848))
    pts = np.random.default_rng(0).uniform([0.3, -0.2, 0.0], [0.6, 0.2, 0.1], (50, 3))
    np.testing.assert_allclose(
        _project(_camera(boxed), pts), (_project(_camera(full), pts) - [448, 100]) / 2, atol=1e-9
    )
    np.testing.assert_allclose(
        _project(_camera(spec), pts), (_project(_camera(full), pts) - [184, 0]) / 2, atol=1e-9
    )
    with pytest.raises(ValueError, match="crop"):
        CameraSpec("bad", FRONT_INTRINSICS, POSE, crop=(500, 0, 400, 480))


def test_rendering_at_output_intrinsics_matches_cropped_downsampled_sensor_image():
    cloud = GaussianCloud.concatenate([table_gaussians(spacing=0.01), backdrop_gaussians(spacing=0.02)])
    full = render(cloud, _camera(CameraSpec("f", FRONT_INTRINSICS, POSE, output_hw=(480, 848)))).rgb
    small = render(cloud, _camera(CameraSpec("f", FRONT_INTRINSICS, POSE, output_hw=(240, 240)))).rgb
    crop = full[:, 184:664]
    box = crop.reshape(240, 2, 240, 2, 3).mean(axis=(1, 3))
    assert np.abs(small - box).mean() < 0.02


def test_wrist_camera_moves_with_its_link(fast_env):
    twin, state = fast_env.twin, fast_env.state
    spec = twin.cameras["wrist"]
    link = twin.robot.link_pose(state.robot.q, spec.mount_link)
    np.testing.assert_allclose(twin.camera(state, "wrist").cam_to_world, link @ spec.pose, atol=1e-12)
    np.testing.assert_allclose(twin.camera(state, "front").cam_to_world, twin.cameras["front"].pose)
