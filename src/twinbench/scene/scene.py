"""Scene: one twin = robot + spring-mass objects + static appearance + cameras.

`Scene.step(action)` advances one control step (30 Hz): controller -> robot tool meshes interpolated
over the physics substeps -> spring-mass frame -> Gaussians follow (FK for robot links, rigid fit or
LBS for objects). `Scene.render()` renders every camera at the policy resolution.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud
from twinbench.gaussians.render import RenderOutput, render
from twinbench.gaussians.skinning import LabelRigidPoser, LBSSkinner, bind
from twinbench.physics import ModelBuilder, SimParams, SpringMassSolver
from twinbench.robot.controller import ControllerConfig, RobotController
from twinbench.robot.gaussians import RobotGaussians
from twinbench.robot.model import RobotModel
from twinbench.scene.cameras import CameraSpec
from twinbench.transforms import fit_rigid_transform, transform_points


@dataclass(frozen=True)
class ObjectSpec:
    """A spring-mass object: particles and Gaussians in the object frame, and its spring network.

    `rigid` objects (uniform high stiffness) carry their Gaussians by the best-fit rigid transform of
    their particles; deformable ones by linear blend skinning.
    """

    name: str
    particles: np.ndarray  # (P, 3) object frame
    gaussians: GaussianCloud  # object frame
    rigid: bool = True
    spring_radius: float = 0.02
    max_neighbors: int = 50
    spring_Y: float = 3e4
    mass: float = 1.0


@dataclass(frozen=True)
class ToolContact:
    """Contact parameters of the robot's tool meshes (pusher, fingers) against object particles."""

    restitution: float = 0.0
    friction: float = 0.5


@dataclass
class _Object:
    spec: ObjectSpec
    start: int  # first particle in the physics model
    count: int
    gaussians: DeviceGaussians | None = None  # views of the scene's Gaussian buffer
    poser: LabelRigidPoser | None = None  # rigid objects
    skinner: LBSSkinner | None = None  # deformable objects
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))


class Scene:
    """A twin: build once, then `reset(...)`, `step(action)`, `render()`."""

    def __init__(
        self,
        robot: RobotModel,
        robot_gaussians: RobotGaussians,
        static_gaussians: GaussianCloud,
        objects: list[ObjectSpec],
        cameras: list[CameraSpec],
        *,
        sim: SimParams | None = None,
        controller: ControllerConfig | None = None,
        tool_contact: ToolContact | None = None,
        image_hw: tuple[int, int] = (240, 240),
        background=(0.45, 0.45, 0.47),
        device: str = "cpu",
    ):
        if not objects:
            raise ValueError("objects: a scene needs at least one spring-mass object")
        names = [o.name for o in objects]
        if len(set(names)) != len(names):
            raise ValueError(f"objects: names must be unique, got {names}")
        self.robot = robot
        self.controller = RobotController(robot, controller)
        self.cameras = list(cameras)
        self.image_hw = tuple(image_hw)
        self.background = background
        self.device = device
        self.sim = sim or SimParams()
        contact = tool_contact or ToolContact()

        builder = ModelBuilder(self.sim)
        self._objects: dict[str, _Object] = {}
        start = 0
        for spec in objects:
            builder.add_body(spec.particles, radius=spec.spring_radius, max_neighbors=spec.max_neighbors,
                             spring_Y=spec.spring_Y, mass=spec.mass)
            self._objects[spec.name] = _Object(spec, start, len(spec.particles))
            start += len(spec.particles)
        q0 = robot.home_q
        self._tool_mesh: dict[str, int] = {}
        for link in robot.contact_links:
            self._tool_mesh[link] = builder.add_kinematic_mesh(
                robot.contact_vertices(q0, link), robot.contact_faces(link),
                restitution=contact.restitution, friction=contact.friction,
            )
        self.model = builder.finalize(device)
        self.solver = SpringMassSolver(self.model)
        self.state = self.model.state()
        self.control = self.model.control()

        # Gaussians: [static | robot | objects...] in one device buffer. The robot's and the objects'
        # segments are rewritten in place every step (FK poses, rigid fits or LBS), on the device.
        parts = [static_gaussians, robot_gaussians.local] + [o.spec.gaussians for o in self._objects.values()]
        self._gaussians: DeviceGaussians = GaussianCloud.concatenate(parts).to_device(device)
        offset = len(static_gaussians) + len(robot_gaussians)
        robot_segment = self._segment(len(static_gaussians), len(robot_gaussians))
        self._robot_poser = robot_gaussians.device_poser(device, out=robot_segment)
        for obj in self._objects.values():
            rest = obj.spec.gaussians
            obj.gaussians = self._segment(offset, len(rest))
            offset += len(rest)
            if obj.spec.rigid:
                obj.poser = LabelRigidPoser(rest, np.zeros(len(rest), np.int32), 1, device, out=obj.gaussians)
            else:
                binding = bind(rest.means, obj.spec.particles, device=device)
                obj.skinner = LBSSkinner(binding, rest.means, rest.quats, device)
        self.frame = 0
        self.finger_forces: tuple[float, float] | None = None

    # ------------------------------------------------------------------ state
    @property
    def object_names(self) -> list[str]:
        return list(self._objects)

    def reset(self, q0: np.ndarray | None = None, object_poses: dict[str, np.ndarray] | None = None) -> None:
        """Robot at q0 (default home), each object at rest at its pose (default identity), zero velocity."""
        self.controller.reset(q0)
        x = self.model.x0_np.copy()
        poses = dict(object_poses or {})
        unknown = set(poses) - set(self._objects)
        if unknown:
            raise ValueError(f"object_poses: unknown objects {sorted(unknown)}; known: {self.object_names}")
        for name, obj in self._objects.items():
            pose = np.asarray(poses.get(name, np.eye(4)), dtype=np.float64)
            if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
                raise ValueError(
                    f"object_poses[{name!r}]: expected a finite 4x4 pose, got shape {pose.shape}"
                )
            x[obj.start: obj.start + obj.count] = transform_points(pose, obj.spec.particles)
        self.state.x.assign(x.astype(np.float32))
        self.state.v.zero_()
        q = self.controller.q
        for link, mid in self._tool_mesh.items():
            verts = self.robot.contact_vertices(q, link)
            self.control.set_kinematic_mesh(mid, verts, verts)
        self.frame = 0
        self.finger_forces = None
        self._update_gaussians()

    @property
    def gaussians(self) -> DeviceGaussians:
        """The scene's Gaussians as rendered: static, then robot, then each object (in order)."""
        return self._gaussians

    def particles(self, name: str) -> np.ndarray:
        """Current world positions (P, 3) of an object's particles."""
        obj = self._objects[name]
        return self.state.x.numpy()[obj.start: obj.start + obj.count].copy()

    def object_pose(self, name: str) -> np.ndarray:
        """Best-fit rigid pose (4x4) of an object's particles relative to its object frame."""
        return self._objects[name].pose.copy()

    # ------------------------------------------------------------------ dynamics
    def step(self, action) -> None:
        """One control step: controller, then one physics frame with the tool meshes swept along.

        Raises `SimulationDiverged` (from the solver) when the simulation blows up; `ValueError` for a
        malformed action.
        """
        cmd = self.controller.step(action, self.finger_forces)
        frames = self.robot.contact_mesh_frames(cmd.q_prev, cmd.q)
        for link, mid in self._tool_mesh.items():
            self.control.set_kinematic_mesh(mid, *frames[link])
        self.solver.simulate_frame(self.state, self.control)
        if self.robot.gripper_joint is not None:  # the fingers' contact force magnitudes, for the latch
            left, right = (float(np.linalg.norm(self.solver.mesh_contact_force(m)))
                           for m in self._tool_mesh.values())
            self.finger_forces = (left, right)
        self.frame += 1
        self._update_gaussians()

    # ------------------------------------------------------------------ appearance
    def _segment(self, start: int, count: int) -> DeviceGaussians:
        """Views of Gaussians [start, start + count) of the scene buffer."""
        g, end = self._gaussians, start + count
        return DeviceGaussians(g.means[start:end], g.quats[start:end], g.scales[start:end],
                               g.opacities[start:end], g.sh[start:end])

    def _update_gaussians(self) -> None:
        self._robot_poser.update(self.robot.fk(self.controller.q))
        x = self.state.x.numpy()
        for obj in self._objects.values():
            p = x[obj.start: obj.start + obj.count]
            obj.pose = fit_rigid_transform(obj.spec.particles, p)
            if obj.poser is not None:
                obj.poser.update(obj.pose[None])
            else:
                particles = self.state.x[obj.start: obj.start + obj.count]  # a view, on the device
                obj.skinner.update(particles, out_means=obj.gaussians.means, out_quats=obj.gaussians.quats)

    def camera(self, spec: CameraSpec):
        """The Camera of a CameraSpec at the current robot configuration and policy resolution."""
        link_pose = None
        if spec.mount_link is not None:
            link_pose = self.robot.link_pose(self.controller.q, spec.mount_link)
        return spec.camera(self.image_hw, link_pose)

    def render(self) -> dict[str, RenderOutput]:
        """Render every camera: {name: RenderOutput (rgb float32 HxWx3, depth, alpha)}."""
        cams = [self.camera(spec) for spec in self.cameras]
        outs = render(self._gaussians, cams, background=self.background, device=self.device)
        return {spec.name: out for spec, out in zip(self.cameras, outs, strict=True)}
