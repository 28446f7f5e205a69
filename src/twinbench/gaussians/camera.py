"""Pinhole camera data object (OpenCV convention: x right, y down, z forward)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from twinbench.transforms import invert_pose

if TYPE_CHECKING:
    from twinbench.gaussians.cloud import GaussianCloud


@dataclass(frozen=True, eq=False)
class Camera:
    """Intrinsics in pixels and a 4x4 camera-to-world pose (compared by identity: it holds an array).

    Pixel (i, j) has its centre at (i+0.5, j+0.5);
    a camera-frame point (x, y, z) projects to u = fx x / z + cx, v = fy y / z + cy."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    cam_to_world: np.ndarray = field(default_factory=lambda: np.eye(4))

    def __post_init__(self) -> None:
        pose = np.asarray(self.cam_to_world, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise ValueError(f"Camera.cam_to_world must be a finite 4x4 matrix, got shape {pose.shape}")
        rot = pose[:3, :3]
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-4) or np.linalg.det(rot) < 0:
            raise ValueError("Camera.cam_to_world: the 3x3 block must be a rotation (orthonormal, det +1)")
        if self.fx <= 0 or self.fy <= 0:
            raise ValueError(f"Camera: fx, fy must be > 0, got {self.fx}, {self.fy}")
        if int(self.width) <= 0 or int(self.height) <= 0:
            raise ValueError(f"Camera: width, height must be > 0, got {self.width}x{self.height}")
        object.__setattr__(self, "cam_to_world", pose)
        object.__setattr__(self, "width", int(self.width))
        object.__setattr__(self, "height", int(self.height))

    @property
    def world_to_cam(self) -> np.ndarray:
        """4x4 world-to-camera matrix (inverse of the rigid pose)."""
        return invert_pose(self.cam_to_world)

    @property
    def position(self) -> np.ndarray:
        return self.cam_to_world[:3, 3].copy()

    @property
    def K(self) -> np.ndarray:
        """3x3 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @staticmethod
    def look_at(
        eye,
        target,
        up=(0.0, 0.0, 1.0),
        *,
        fx: float,
        fy: float | None = None,
        width: int,
        height: int,
        cx: float | None = None,
        cy: float | None = None,
    ) -> Camera:
        """Camera at `eye` looking at `target`; image 'up' (-y) is as close to `up` as possible.
        cx, cy default to the image centre, fy to fx."""
        pose = look_at_pose(eye, target, up)
        return Camera(
            fx=fx,
            fy=fx if fy is None else fy,
            cx=width / 2 if cx is None else cx,
            cy=height / 2 if cy is None else cy,
            width=width,
            height=height,
            cam_to_world=pose,
        )


def look_at_pose(eye, target, up=(0.0, 0.0, 1.0)) -> np.ndarray:
    """Camera-to-world pose (OpenCV axes) at `eye` looking at `target`, image 'up' as close to `up` as
    possible."""
    eye = np.asarray(eye, dtype=np.float64)
    forward = np.asarray(target, dtype=np.float64) - eye
    if np.linalg.norm(forward) < 1e-12:
        raise ValueError("look_at: eye and target coincide")
    forward /= np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, dtype=np.float64))
    if np.linalg.norm(right) < 1e-9:
        raise ValueError("look_at: `up` is parallel to the viewing direction; pass another up")
    right /= np.linalg.norm(right)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = right, np.cross(forward, right), forward, eye
    return pose


def framing_camera(
    cloud: GaussianCloud,
    *,
    width: int,
    height: int,
    fov_deg: float = 60.0,
    view_dir=(0.0, -1.0, 0.6),
    up=(0.0, 0.0, 1.0),
    percentile: float = 95.0,
) -> Camera:
    """A camera looking at the median centre from `view_dir`, far enough that the sphere holding
    `percentile` % of the means fits in the narrower field of view."""
    if len(cloud) == 0:
        raise ValueError("cannot frame an empty cloud")
    if not 0 < fov_deg < 180:
        raise ValueError(f"fov_deg must be in (0, 180), got {fov_deg}")
    centre = np.median(cloud.means, axis=0)
    radius = float(np.percentile(np.linalg.norm(cloud.means - centre, axis=1), percentile))
    radius = max(radius, 1e-3)
    fx = 0.5 * width / np.tan(np.radians(fov_deg) / 2)
    half_fov = min(np.arctan(0.5 * width / fx), np.arctan(0.5 * height / fx))
    d = np.asarray(view_dir, dtype=np.float64)
    if np.linalg.norm(d) < 1e-12:
        raise ValueError("view_dir must be non-zero")
    eye = centre + d / np.linalg.norm(d) * radius / np.sin(half_fov) * 1.05
    return Camera.look_at(eye, centre, up, fx=fx, width=width, height=height)
