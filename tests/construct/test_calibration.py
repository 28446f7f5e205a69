"""Camera calibration import: intrinsics, extrinsics (OpenCV / OpenGL axes, another world frame) and
the wrist camera's hand-eye transform."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twinbench.construct.calibration import OPENGL_TO_OPENCV, load_calibration
from twinbench.gaussians.camera import look_at_pose


def test_cameras_are_read_into_the_robot_base_frame(tmp_path):
    c2w = look_at_pose((0.9, -0.4, 0.5), (0.45, 0.0, 0.0))
    base_to_world = np.eye(4)
    base_to_world[:3, 3] = [0.1, 0.2, 0.0]
    hand_eye = np.eye(4)
    hand_eye[:3, 3] = [0.0, -0.07, -0.02]
    doc = {
        "base_to_world": base_to_world.tolist(),
        "cameras": [
            {"name": "front", "K": [[427.3, 0, 430.0], [0, 426.8, 242.8], [0, 0, 1]],
             "sensor_size": [848, 480], "camera_to_world": (base_to_world @ c2w).tolist()},
            {"name": "gl", "intrinsics": [400, 400, 320, 240], "sensor_size": [640, 480],
             "world_to_camera": np.linalg.inv(base_to_world @ c2w @ OPENGL_TO_OPENCV).tolist(),
             "axes": "opengl"},
            {"name": "wrist", "intrinsics": [433.3, 433.3, 425.7, 244.7], "hand_eye": hand_eye.tolist(),
             "mount_link": "link7", "output_hw": [120, 212]},
        ],
    }
    (tmp_path / "calib.json").write_text(json.dumps(doc))
    front, gl, wrist = load_calibration(tmp_path / "calib.json")
    assert front.intrinsics == (427.3, 426.8, 430.0, 242.8)
    np.testing.assert_allclose(front.pose, c2w, atol=1e-9)
    np.testing.assert_allclose(gl.pose, c2w, atol=1e-9)  # OpenGL axes converted to OpenCV
    assert wrist.mount_link == "link7" and wrist.output_hw == (120, 212)
    np.testing.assert_allclose(wrist.pose, hand_eye)


@pytest.mark.parametrize("cam, match", [
    ({"name": "a", "intrinsics": [1, 1, 0, 0]}, "exactly one of camera_to_world"),
    ({"name": "a", "intrinsics": [1, 1, 0, 0], "hand_eye": np.eye(4).tolist()}, "mount_link"),
    ({"name": "a", "camera_to_world": np.eye(4).tolist()}, "'intrinsics'"),
    ({"name": "a", "intrinsics": [1, 1, 0, 0], "camera_to_world": np.diag([1, 1, -1, 1]).tolist()},
     "rotation"),
    ({"name": "a", "focal": 3}, "unknown field"),
])
def test_bad_calibration_is_named(tmp_path, cam, match):
    (tmp_path / "c.json").write_text(json.dumps({"cameras": [cam]}))
    with pytest.raises(ValueError, match=match):
        load_calibration(tmp_path / "c.json")
