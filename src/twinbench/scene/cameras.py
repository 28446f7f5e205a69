"""Scene cameras: reference intrinsics, fixed and wrist-mounted cameras, policy-resolution output.

A policy never sees the 848x480 sensor image: it sees a centre crop resized to 240x240 (or a plain
resize to 120x212). Cropping and resizing a pinhole image is itself a pinhole camera, so the scene
renders directly at the policy resolution with adjusted intrinsics instead of rendering the full sensor
image and resampling it (same pixels up to resampling, several times cheaper).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinbench.gaussians.camera import Camera, look_at_pose

SENSOR_SIZE = (848, 480)  # width, height of both reference cameras
# (fx, fy, cx, cy) of the reference cell's cameras (DESIGN §5).
FRONT_INTRINSICS = (427.29, 426.79, 430.00, 242.81)
WRIST_INTRINSICS = (433.26, 433.26, 425.70, 244.70)


def policy_intrinsics(
    intrinsics: tuple[float, float, float, float],
    sensor_size: tuple[int, int],
    out_hw: tuple[int, int],
) -> tuple[float, float, float, float]:
    """Intrinsics of the sensor image centre-cropped to the output aspect ratio, then resized to out_hw.

    out_hw = (H, W). (240, 240) takes the central 480x480 square of an 848x480 image; (120, 212) is a
    plain 1/4 resize (same aspect ratio).
    """
    fx, fy, cx, cy = intrinsics
    sw, sh = sensor_size
    oh, ow = out_hw
    if min(oh, ow, sw, sh) <= 0:
        raise ValueError(f"sizes must be positive, got sensor {sensor_size}, output (H, W) {out_hw}")
    # Largest crop of the output's aspect ratio centred in the sensor.
    crop_w = min(sw, sh * ow / oh)
    crop_h = crop_w * oh / ow
    x0, y0 = (sw - crop_w) / 2, (sh - crop_h) / 2
    s = ow / crop_w
    return fx * s, fy * s, (cx - x0) * s, (cy - y0) * s


@dataclass(frozen=True)
class CameraSpec:
    """A named scene camera.

    Fixed: `cam_to_world` (4x4, OpenCV axes: x right, y down, z forward). Wrist: `mount_link` names a robot
    link and `cam_to_world` is then the camera pose in that link's frame.
    """

    name: str
    intrinsics: tuple[float, float, float, float]
    cam_to_world: np.ndarray
    sensor_size: tuple[int, int] = SENSOR_SIZE
    mount_link: str | None = None

    def camera(self, out_hw: tuple[int, int], link_pose: np.ndarray | None = None) -> Camera:
        """The Camera rendering this view at the policy resolution out_hw = (H, W)."""
        pose = np.asarray(self.cam_to_world, dtype=np.float64)
        if self.mount_link is not None:
            if link_pose is None:
                raise ValueError(
                    f"camera {self.name!r} is mounted on link {self.mount_link!r}: pass link_pose"
                )
            pose = np.asarray(link_pose, dtype=np.float64) @ pose
        fx, fy, cx, cy = policy_intrinsics(self.intrinsics, self.sensor_size, out_hw)
        return Camera(fx=fx, fy=fy, cx=cx, cy=cy, width=out_hw[1], height=out_hw[0], cam_to_world=pose)


def front_camera(eye=(0.92, -0.42, 0.52), target=(0.46, 0.0, 0.0)) -> CameraSpec:
    """The fixed external camera: front-left of the table, looking down at the workspace."""
    return CameraSpec("front", FRONT_INTRINSICS, look_at_pose(eye, target))


def wrist_camera(mount_link: str, offset=(0.0, -0.07, -0.02), look=(0.0, 0.0, 0.12)) -> CameraSpec:
    """A camera fixed to `mount_link` at `offset` (link frame), looking at the point `look` (link frame).

    With the built-in arm's flange frame (z along the tool), the defaults look past the tool tip.
    """
    return CameraSpec(
        "wrist", WRIST_INTRINSICS, look_at_pose(offset, look, up=(1.0, 0.0, 0.0)), mount_link=mount_link
    )
