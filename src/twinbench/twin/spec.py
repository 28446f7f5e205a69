"""TwinSpec: everything a twin is made of, as frozen dataclasses of plain data (DESIGN §12).

A spec holds arrays, Gaussian clouds and meshes themselves, not file names: the built-in cells make one
in code, `twinbench.twin.files.load_twin` reads one from a twin directory, and `build_twin` turns
either into a running `Twin`. World frame = robot base frame (z up, table at z = 0, DESIGN §3): a scan
is registered into the robot base frame when the twin is made, so a spec has no separate base pose.

Geometry that task rules read is data too: an object's footprint (`ObjectSpec.outline`), the pusher
tip's radius (`RobotSpec.tool_radius`) and a collider's channel (`ColliderSpec.channel`).

Contact: the robot's tool meshes have `RobotSpec.tool_contact`; each static collider its own
restitution and friction; ground and particle-particle contact are per twin (`SimParams`, as in a
PhysTwin case).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twinbench.errors import check_name
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.colormap import apply_color_map, check_color_map
from twinbench.gaussians.response import CameraResponse
from twinbench.physics import SimParams
from twinbench.robot.controller import ControllerConfig
from twinbench.twin.shapes import Outline

BINDINGS = ("rigid", "lbs")
CONTACT_MESHES = ("collision", "convex_hull")  # RobotSpec.contact_mesh
BUILTIN_ROBOTS = {
    "builtin:xarm7_pusher": "pusher", "builtin:xarm7_pusher20": "pusher20", "builtin:xarm7_gripper": "gripper"
}


def _pose(name: str, value) -> np.ndarray:
    p = np.asarray(value, dtype=np.float64)
    if p.shape != (4, 4) or not np.all(np.isfinite(p)):
        raise ValueError(f"{name}: expected a finite 4x4 pose, got shape {p.shape}")
    r = p[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0 or np.any(p[3] != [0, 0, 0, 1]):
        raise ValueError(f"{name}: the 4x4 pose must be rigid (rotation block, last row 0 0 0 1)")
    return p


@dataclass(frozen=True, eq=False)
class ColorMap:
    """A polynomial colour map (`twinbench.gaussians.colormap`): coefficients (3, F) of degree `degree`."""

    degree: int
    coeffs: np.ndarray

    def __post_init__(self) -> None:
        object.__setattr__(self, "coeffs", check_color_map(self.coeffs, self.degree))

    def apply(self, cloud: GaussianCloud) -> GaussianCloud:
        return apply_color_map(cloud, self.coeffs, self.degree)


def with_color_map(cloud: GaussianCloud | None, color_map: ColorMap | None) -> GaussianCloud | None:
    """`cloud` with `color_map` applied (either may be None)."""
    return cloud if cloud is None or color_map is None else color_map.apply(cloud)


@dataclass(frozen=True)
class ContactSpec:
    """Restitution in [0, 1] and friction in [0, 2] of a contact pair (DESIGN §4)."""

    restitution: float = 0.0
    friction: float = 0.5

    def __post_init__(self) -> None:
        if not 0.0 <= self.restitution <= 1.0 or not 0.0 <= self.friction <= 2.0:
            raise ValueError(
                f"contact: need restitution in [0, 1] and friction in [0, 2], got "
                f"{self.restitution}, {self.friction}"
            )


@dataclass(frozen=True, eq=False)
class RobotSpec:
    """The robot: its URDF (a path, or a built-in name `builtin:xarm7_pusher`, `builtin:xarm7_pusher20` (the
    reference study's 20 cm pusher) or `builtin:xarm7_gripper`), end-effector and contact links, gripper
    joint, and its Gaussians.

    Gaussians: a registered scan in the world frame at configuration `gaussians_q` (default `home_q`),
    each labelled with a link (`gaussian_labels` index `gaussian_links`); or, when `gaussians` is None,
    discs sampled on the URDF's visual meshes every `scan_spacing` metres (built-in robots).

    `contact_mesh`: how the contact links collide with objects: "collision" (their URDF collision meshes
    as they are) or "convex_hull" (each one's convex hull, simplified to at most 1,000 faces: for CAD
    meshes, whose tens of thousands of faces make every physics substep slow; see
    `RobotModel.with_convex_contacts`).

    `tool_radius`: the radius (m) of the tool tip that pushes (a pusher rod; None for other tools). The
    built-in pushers' is their rod's (`twinbench.robot.builtin.PUSHERS`), filled in when omitted.
    """

    urdf: str
    ee_link: str | None = None
    contact_links: tuple[str, ...] = ()
    gripper_joint: str | None = None
    gripper_open: float | None = None
    gripper_closed: float | None = None
    home_q: tuple[float, ...] | None = None
    gaussians: GaussianCloud | None = None
    gaussian_labels: np.ndarray | None = None
    gaussian_links: tuple[str, ...] = ()
    gaussians_q: tuple[float, ...] | None = None
    scan_spacing: float = 0.006
    tool_contact: ContactSpec = field(default_factory=ContactSpec)
    color_map: ColorMap | None = None
    tool_radius: float | None = None
    # added after twins were hashed: left out of `twin_spec_hash` at its default, so hashes stay as they were
    contact_mesh: str = field(default="collision", metadata={"hash_unless_default": True})

    def __post_init__(self) -> None:
        if self.contact_mesh not in CONTACT_MESHES:
            raise ValueError(
                f"robot.contact_mesh: expected one of {list(CONTACT_MESHES)}, got {self.contact_mesh!r}"
            )
        if not isinstance(self.urdf, str) or not self.urdf:
            raise ValueError("robot.urdf: give a URDF path or a built-in name " + str(sorted(BUILTIN_ROBOTS)))
        if self.urdf.startswith("builtin:") and self.urdf not in BUILTIN_ROBOTS:
            raise ValueError(
                f"robot.urdf: unknown built-in robot {self.urdf!r}; known: {sorted(BUILTIN_ROBOTS)}"
            )
        if self.gaussians is None:
            if not self.scan_spacing > 0:
                raise ValueError(f"robot.scan_spacing: must be > 0, got {self.scan_spacing}")
        else:
            labels = np.asarray(self.gaussian_labels)
            if labels.shape != (len(self.gaussians),) or not np.issubdtype(labels.dtype, np.integer):
                raise ValueError(
                    f"robot.gaussian_labels: expected ({len(self.gaussians)},) integers "
                    f"(one link per Gaussian), got {labels.shape} {labels.dtype}"
                )
            if labels.size and (labels.min() < 0 or labels.max() >= len(self.gaussian_links)):
                raise ValueError(
                    f"robot.gaussian_labels: values must index robot.gaussian_links "
                    f"(0..{len(self.gaussian_links) - 1})"
                )
            object.__setattr__(self, "gaussian_labels", labels.astype(np.int32))
        if self.tool_radius is not None and not (np.isfinite(self.tool_radius) and self.tool_radius > 0):
            raise ValueError(
                f"robot.tool_radius: expected a finite radius > 0 (m) or null, got {self.tool_radius!r}"
            )
        if self.builtin_tool in ("pusher", "pusher20"):
            from twinbench.robot.builtin import PUSHERS

            radius = PUSHERS[self.builtin_tool][0]
            if self.tool_radius is None:
                object.__setattr__(self, "tool_radius", radius)
            elif self.tool_radius != radius:
                raise ValueError(
                    f"robot.tool_radius: the built-in pusher's rod has radius {radius} m, got "
                    f"{self.tool_radius}; omit it, or give the URDF of your own tool"
                )

    @property
    def builtin_tool(self) -> str | None:
        return BUILTIN_ROBOTS.get(self.urdf)


@dataclass(frozen=True, eq=False)
class ObjectSpec:
    """A spring-mass object (DESIGN §4): particles in its own frame, springs, masses, Gaussians.

    Springs are explicit (`springs` (M, 2) local indices, optional `rest_lengths`, `spring_Y` scalar or
    per spring: PhysTwin's trained twins) or made by the radius rule (`spring_radius`, `max_neighbors`,
    `spring_Y`). `binding`: "rigid" (Gaussians follow the particles' best-fit rigid motion) or "lbs"
    (linear blend skinning). `rest_pose` places the object frame in the world at rest. `outline`: the
    object's footprint as a prism in its own frame (`twinbench.twin.shapes.Outline`), for tasks that
    reason about its shape (push-T); None when not given. `goal_pose`: where a task that moves the object
    should bring it (push-T's goal), a world pose; None: its rest pose.
    """

    name: str
    particles: np.ndarray
    springs: np.ndarray | None = None
    rest_lengths: np.ndarray | None = None
    spring_Y: float | np.ndarray = 3e4
    spring_radius: float = 0.02
    max_neighbors: int = 30
    mass: float | np.ndarray = 1.0
    gaussians: GaussianCloud | None = None
    binding: str = "lbs"
    rest_pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    color_map: ColorMap | None = None
    outline: Outline | None = None
    goal_pose: np.ndarray | None = None

    def __post_init__(self) -> None:
        where = f"objects[{self.name!r}]"
        check_name(self.name, "objects: name")  # it names the object's files
        p = np.asarray(self.particles)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) == 0 or not np.all(np.isfinite(p)):
            raise ValueError(f"{where}.particles: expected a finite (P, 3) array, got shape {p.shape}")
        if self.binding not in BINDINGS:
            raise ValueError(f"{where}.binding: expected one of {BINDINGS}, got {self.binding!r}")
        object.__setattr__(self, "rest_pose", _pose(f"{where}.rest_pose", self.rest_pose))
        if self.goal_pose is not None:
            object.__setattr__(self, "goal_pose", _pose(f"{where}.goal_pose", self.goal_pose))
        if self.outline is not None and not isinstance(self.outline, Outline):
            raise ValueError(f"{where}.outline: expected a twinbench.twin.shapes.Outline or None, "
                             f"got {type(self.outline).__name__}")
        if self.springs is not None:
            s = np.asarray(self.springs)
            if s.ndim != 2 or s.shape[1] != 2 or (s.size and not np.issubdtype(s.dtype, np.integer)):
                raise ValueError(
                    f"{where}.springs: expected an (M, 2) integer array, got {s.shape} {s.dtype}"
                )
            if s.size and (s.min() < 0 or s.max() >= len(p)):
                raise ValueError(
                    f"{where}.springs: indices must lie in [0, {len(p)}) (the object's particles)"
                )
            for name, n in (("rest_lengths", len(s)),):
                v = getattr(self, name)
                if v is not None and np.shape(v) != (n,):
                    raise ValueError(f"{where}.{name}: expected shape ({n},), got {np.shape(v)}")
        for name, n in (("spring_Y", None if self.springs is None else len(self.springs)), ("mass", len(p))):
            v = np.asarray(getattr(self, name), dtype=np.float64)
            if v.ndim and (n is None or v.shape != (n,)):
                raise ValueError(f"{where}.{name}: expected a scalar or shape ({n},), got {v.shape}")
            if not np.all(np.isfinite(v)) or np.any(v <= 0):
                raise ValueError(f"{where}.{name}: values must be finite and > 0")

    @property
    def num_particles(self) -> int:
        return int(len(self.particles))

    @property
    def rest_gaussians(self) -> GaussianCloud | None:
        """Gaussians in the object frame with the colour map applied."""
        return with_color_map(self.gaussians, self.color_map)


@dataclass(frozen=True, eq=False)
class ColliderSpec:
    """A static triangle-mesh collider (box, clip, table edge) placed at `pose`, with optional Gaussians
    in its own frame. `channel` = (width, depth, length), m: a channel the collider forms along its
    frame's y axis, centred on its origin, floor at z = 0, open at both ends (the rope-routing clip; its
    end planes are the openings); None when it has none."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    contact: ContactSpec = field(default_factory=ContactSpec)
    gaussians: GaussianCloud | None = None
    color_map: ColorMap | None = None
    channel: tuple[float, float, float] | None = None

    def __post_init__(self) -> None:
        where = f"colliders[{check_name(self.name, 'colliders: name')!r}]"  # it names files
        v, f = np.asarray(self.vertices), np.asarray(self.faces)
        if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3 or not np.all(np.isfinite(v)):
            raise ValueError(f"{where}.mesh: expected finite (V, 3) vertices, got {v.shape}")
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0 or f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"{where}.mesh: expected (F, 3) faces indexing the {len(v)} vertices")
        object.__setattr__(self, "pose", _pose(f"{where}.pose", self.pose))
        if self.channel is not None:
            c = np.asarray(self.channel, dtype=np.float64)
            if c.shape != (3,) or not np.all(np.isfinite(c)) or np.any(c <= 0):
                raise ValueError(f"{where}.channel: expected (width, depth, length) > 0 in metres, "
                                 f"got {self.channel!r}")
            object.__setattr__(self, "channel", tuple(float(v) for v in c))


@dataclass(frozen=True, eq=False)
class CameraSpec:
    """A camera: pinhole intrinsics of its sensor, a pose, and what the policy sees.

    `pose` is camera-to-world (OpenCV axes: x right, y down, z forward), or, for a camera on the robot
    (`mount_link`), the camera pose in that link's frame. The image is the sensor's `crop` (x0, y0, w, h
    in sensor pixels; None = the largest centre crop of the output's aspect ratio) resized to
    `output_hw` = (H, W); the twin renders it directly with the equivalent intrinsics. `response`: the
    camera's response (`twinbench.gaussians.response`), applied by TwinEnv after rendering; None = none.
    """

    name: str
    intrinsics: tuple[float, float, float, float]
    pose: np.ndarray
    sensor_size: tuple[int, int] = (848, 480)
    mount_link: str | None = None
    crop: tuple[float, float, float, float] | None = None
    output_hw: tuple[int, int] = (240, 240)
    depth: bool = False
    response: CameraResponse | None = None

    def __post_init__(self) -> None:
        where = f"cameras[{check_name(self.name, 'cameras: name')!r}]"  # it names image files
        if self.response is not None and not isinstance(self.response, CameraResponse):
            raise ValueError(f"{where}.response: expected a CameraResponse or None, "
                             f"got {type(self.response).__name__}")
        k = np.asarray(self.intrinsics, dtype=np.float64)
        if k.shape != (4,) or not np.all(np.isfinite(k)) or k[0] <= 0 or k[1] <= 0:
            raise ValueError(f"{where}.intrinsics: expected [fx, fy, cx, cy] with fx, fy > 0")
        object.__setattr__(self, "pose", _pose(f"{where}.pose", self.pose))
        sw, sh = self.sensor_size
        oh, ow = self.output_hw
        if min(sw, sh, oh, ow) <= 0 or max(oh, ow) > 8192:
            raise ValueError(
                f"{where}: sensor_size and output_hw must be positive (output <= 8192 px), "
                f"got {self.sensor_size}, {self.output_hw}"
            )
        if self.crop is not None:
            object.__setattr__(self, "crop", tuple(float(v) for v in self.crop))  # as twin.json reads it back
            x0, y0, w, h = self.crop
            if w <= 0 or h <= 0 or x0 < 0 or y0 < 0 or x0 + w > sw + 1e-9 or y0 + h > sh + 1e-9:
                raise ValueError(f"{where}.crop: [x0, y0, w, h] must lie inside the {sw}x{sh} sensor")

    def crop_box(self) -> tuple[float, float, float, float]:
        """(x0, y0, w, h) of the sensor region the policy image shows."""
        if self.crop is not None:
            return tuple(float(v) for v in self.crop)
        sw, sh = self.sensor_size
        oh, ow = self.output_hw
        crop_w = min(sw, sh * ow / oh)  # largest crop of the output's aspect ratio, centred
        crop_h = crop_w * oh / ow
        return (sw - crop_w) / 2, (sh - crop_h) / 2, crop_w, crop_h

    def output_intrinsics(self) -> tuple[float, float, float, float]:
        """(fx, fy, cx, cy) of the cropped and resized image (cropping and resizing keep a pinhole camera)."""
        fx, fy, cx, cy = self.intrinsics
        x0, y0, w, h = self.crop_box()
        sx, sy = self.output_hw[1] / w, self.output_hw[0] / h
        return fx * sx, fy * sy, (cx - x0) * sx, (cy - y0) * sy

    def view(self, cam_to_world: np.ndarray | None = None):
        """The `gaussians.camera.Camera` of the output image, at `cam_to_world` (default: `pose`, a static
        camera's world pose; a mounted camera's world pose is its link's pose @ `pose`)."""
        from twinbench.gaussians.camera import Camera

        fx, fy, cx, cy = self.output_intrinsics()
        h, w = self.output_hw
        return Camera(fx=fx, fy=fy, cx=cx, cy=cy, width=w, height=h,
                      cam_to_world=self.pose if cam_to_world is None else cam_to_world)


@dataclass(frozen=True, eq=False)
class TwinSpec:
    """A whole twin: robot, static appearance, spring-mass objects, colliders, cameras and settings."""

    name: str
    robot: RobotSpec
    objects: tuple[ObjectSpec, ...] = ()
    cameras: tuple[CameraSpec, ...] = ()
    background: GaussianCloud | None = None
    background_color_map: ColorMap | None = None
    colliders: tuple[ColliderSpec, ...] = ()
    sim: SimParams = field(default_factory=SimParams)
    controller: ControllerConfig = field(default_factory=ControllerConfig)
    render_background: tuple[float, float, float] = (0.45, 0.45, 0.47)

    def __post_init__(self) -> None:
        check_name(self.name, "name")  # it names output folders
        object.__setattr__(self, "objects", tuple(self.objects))
        object.__setattr__(self, "cameras", tuple(self.cameras))
        object.__setattr__(self, "colliders", tuple(self.colliders))
        for kind, items in (
            ("objects and colliders", self.objects + self.colliders),
            ("cameras", self.cameras),
        ):
            names = [it.name for it in items]
            if len(set(names)) != len(names):
                raise ValueError(f"{kind}: names must be unique, got {names}")
        if not self.objects:
            raise ValueError("objects: a twin needs at least one spring-mass object")
        if not self.cameras:
            raise ValueError("cameras: a twin needs at least one camera")

    def object(self, name: str) -> ObjectSpec:
        for o in self.objects:
            if o.name == name:
                return o
        raise KeyError(
            f"twin {self.name!r} has no object {name!r}; objects: {[o.name for o in self.objects]}"
        )

    def camera(self, name: str) -> CameraSpec:
        for c in self.cameras:
            if c.name == name:
                return c
        raise KeyError(
            f"twin {self.name!r} has no camera {name!r}; cameras: {[c.name for c in self.cameras]}"
        )
