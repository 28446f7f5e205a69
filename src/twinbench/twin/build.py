"""build_twin: a TwinSpec made runnable. `Twin` is the immutable part (spring-mass model and solver, robot
model and controller, rest Gaussians, cameras); `TwinState` is what changes per step (particles,
velocities, kinematic-mesh targets, controller state, posed Gaussians).

    twin, state = build_twin(spec, device="cpu")
    twin.reset(state, q0, {"tblock": pose})       # robot at q0, objects at rest at their poses
    twin.step(state, action)                      # controller -> tool meshes swept over the substeps -> frame
    frames = twin.render(state)                   # {camera: RenderOutput}, Gaussians posed first

    twin, states = build_twin(spec, num_worlds=16)   # one TwinState per world, physics in one launch
    results = twin.step_worlds(states, actions)       # per world: RobotCommand or SimulationDiverged
    frames = twin.render_worlds(states)               # per world {camera: RenderOutput}, one render call

Worlds: the model holds `num_worlds` independent copies of the objects and tool meshes (world-major),
so every kernel of a frame runs all worlds in one launch; each world's `TwinState` is a view of world
`state.world` of the shared physics buffers plus its own robot and poses; its Gaussians are world
`state.world` of one buffer that `pose_worlds` poses for all worlds in one launch per poser. A world
computes bit for bit what a one-world twin computes, and a world that diverges ends alone (its result is
the error).

Per step: the controller turns the action into joint targets (IK + velocity-control mimic + gripper
latch, DESIGN §5), the tool meshes' vertices are interpolated over the physics substeps, one spring-mass
frame runs, and the fingers' contact forces feed the latch on the next step. Rendering poses the
Gaussians from the state (robot links by FK, rigid objects by the best-fit rigid motion of their
particles, deformable ones by LBS) into the state's Gaussian buffer, then renders the cameras; for a camera
that has not moved, the background's render work is kept (`twin.render_cache`, shared by the worlds; on
CPU only, where it pays; set it to None for full renders: the images are the same).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import warp as wp

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud, SplitGaussians
from twinbench.gaussians.render import RenderCache, RenderOutput, render_batch
from twinbench.gaussians.skinning import LabelRigidPoser, LBSSkinner, bind
from twinbench.physics import (
    Control,
    ModelBuilder,
    SimulationDiverged,
    SpringMassModel,
    SpringMassSolver,
    State,
    check_device,
    check_divergence,
)
from twinbench.robot.controller import ControllerState, RobotCommand, RobotController
from twinbench.robot.gaussians import RobotGaussians, sample_robot_scan
from twinbench.robot.model import HEAVY_CONTACT_FACES, RobotModel
from twinbench.transforms import fit_rigid_transform, transform_points
from twinbench.twin.spec import CameraSpec, RobotSpec, TwinSpec, with_color_map


class _PosedGaussians:
    """The posed Gaussians of every world of one set of states, world after world in one buffer (made on
    first use), so that each poser runs once for all worlds."""

    def __init__(self) -> None:
        self.all: DeviceGaussians | None = None


@dataclass
class TwinState:
    """Everything of one world that changes while a twin runs. Read it through the Twin's accessors
    (`particles`, `object_pose`, `ee_state`, ...) so task code does not depend on its layout."""

    physics: State  # particle positions and velocities (of every world; this one is `world`)
    control: Control  # this frame's kinematic-mesh vertex targets (robot tools), every world
    robot: ControllerState  # joint configuration, gripper command, latch
    gaussians: DeviceGaussians | None = None  # the scene's Gaussians, posed (made on first use)
    world: int = 0
    posed: _PosedGaussians = field(default_factory=_PosedGaussians, repr=False)  # shared by the worlds
    object_poses: dict[str, np.ndarray] = field(default_factory=dict)  # best-fit rigid pose per object
    collider_poses: dict[str, np.ndarray] = field(default_factory=dict)  # this episode's collider poses
    finger_forces: tuple[float, float] | None = None  # last frame's contact force per finger (N)
    command: RobotCommand | None = None  # the controller's last command
    frame: int = 0


@dataclass(frozen=True)
class _ObjectSlot:
    name: str
    start: int  # first particle in the spring-mass model
    count: int
    g_start: int  # first Gaussian in the scene buffer
    g_count: int
    rest_particles: np.ndarray  # (P, 3) object frame
    rest_pose: np.ndarray


def load_spec_robot(spec: RobotSpec) -> RobotModel:
    """The RobotModel of a RobotSpec (a built-in arm or a URDF file)."""
    from twinbench.robot.builtin import load_builtin_arm
    from twinbench.robot.model import load_robot

    if spec.builtin_tool is not None:
        model = load_builtin_arm(spec.builtin_tool)
        overrides = {
            k: getattr(spec, k)
            for k in ("ee_link", "gripper_joint", "gripper_open", "gripper_closed")
            if getattr(spec, k) is not None
        }
        if spec.contact_links:
            overrides["contact_links"] = tuple(spec.contact_links)
        if spec.home_q is not None:
            overrides["home_q"] = np.asarray(spec.home_q, dtype=np.float64)
        if overrides:
            model = load_robot(
                model.urdf_path,
                **{
                    "ee_link": model.ee_link,
                    "gripper_joint": model.gripper_joint,
                    "gripper_open": model.gripper_open,
                    "gripper_closed": model.gripper_closed,
                    "contact_links": model.contact_links,
                    "home_q": model.home_q,
                    **overrides,
                },
            )
    else:
        model = load_robot(
            spec.urdf,
            ee_link=spec.ee_link,
            gripper_joint=spec.gripper_joint,
            gripper_open=spec.gripper_open,
            gripper_closed=spec.gripper_closed,
            contact_links=spec.contact_links,
            home_q=None if spec.home_q is None else np.asarray(spec.home_q, dtype=np.float64),
        )
    return model.with_convex_contacts() if spec.contact_mesh == "convex_hull" else model


def warn_heavy_contact_mesh(model: RobotModel, link: str) -> None:
    """Every physics substep moves a contact link's mesh and refits its BVH (~0.1 us a face on a CPU core,
    667 substeps a frame at the cells' dt): a CAD mesh from a user's URDF (an SO-101's gripper and jaw,
    76k faces together) made an env step 8.7 s against the built-in pusher's 0.12 s."""
    n = len(model.contact_faces(link))
    if n > HEAVY_CONTACT_FACES:
        import warnings

        warnings.warn(f"{model.urdf_path}: contact link {link!r} has a collision mesh of {n:,} faces, "
                      "refitted every physics substep: steps will be slow; set robot.contact_mesh to "
                      '"convex_hull" in the twin (or its build config) to collide through its simplified '
                      f"convex hull, or give the link a <collision> mesh of at most {HEAVY_CONTACT_FACES:,} "
                      "faces",
                      stacklevel=3)


def _robot_gaussians(spec: RobotSpec, model: RobotModel) -> RobotGaussians:
    if spec.gaussians is None:
        rg = sample_robot_scan(model, spacing=spec.scan_spacing)
        local = rg.local
        link_index = rg.link_index
    else:
        missing = [name for name in spec.gaussian_links if name not in model.link_names]
        if missing:
            raise ValueError(
                f"robot.gaussians.links: {missing} are not links of {model.urdf_path.name} "
                f"(links: {model.link_names})"
            )
        to_model = np.array([model.link_index(name) for name in spec.gaussian_links], dtype=np.int64)
        q = None if spec.gaussians_q is None else np.asarray(spec.gaussians_q, dtype=np.float64)
        rg = RobotGaussians.from_world(model, spec.gaussians, to_model[spec.gaussian_labels], q)
        local, link_index = rg.local, rg.link_index
    if spec.color_map is not None:
        local = spec.color_map.apply(local)
    return RobotGaussians(model, local, link_index)


class Twin:
    """A built twin (see the module docstring). Immutable after `build_twin`; all per-world quantities
    live in a `TwinState` (`new_state()`)."""

    def __init__(self, spec: TwinSpec, device: str = "cpu", num_worlds: int = 1):
        self.spec = spec
        self.device = check_device(device)
        self.robot: RobotModel = load_spec_robot(spec.robot)
        self.controller = RobotController(self.robot, spec.controller)
        for cam in spec.cameras:
            if cam.mount_link is not None and cam.mount_link not in self.robot.link_names:
                raise ValueError(
                    f"cameras[{cam.name!r}].mount_link: {cam.mount_link!r} is not a robot link "
                    f"(links: {self.robot.link_names})"
                )
        self.cameras: dict[str, CameraSpec] = {c.name: c for c in spec.cameras}

        builder = ModelBuilder(spec.sim)
        slots, start = [], 0
        for obj in spec.objects:
            builder.add_body(
                obj.particles,
                radius=obj.spring_radius,
                max_neighbors=obj.max_neighbors,
                spring_Y=obj.spring_Y,
                mass=obj.mass,
                springs=obj.springs,
                rest_lengths=obj.rest_lengths,
            )
            slots.append((obj, start))
            start += obj.num_particles
        q0 = self.robot.home_q
        tool = spec.robot.tool_contact
        self._tool_mesh: dict[str, int] = {}
        for link in self.robot.contact_links:
            warn_heavy_contact_mesh(self.robot, link)
            self._tool_mesh[link] = builder.add_kinematic_mesh(
                self.robot.contact_vertices(q0, link),
                self.robot.contact_faces(link),
                restitution=tool.restitution,
                friction=tool.friction,
            )
        # Colliders are placed per episode (a task may move the box), so they are kinematic meshes whose
        # vertices live in the state's control, held still within an episode.
        self._collider_mesh: dict[str, int] = {}
        for col in spec.colliders:
            self._collider_mesh[col.name] = builder.add_kinematic_mesh(
                transform_points(col.pose, col.vertices),
                col.faces,
                restitution=col.contact.restitution,
                friction=col.contact.friction,
            )
        self.model: SpringMassModel = builder.finalize(device, num_worlds=num_worlds)
        self.solver = SpringMassSolver(self.model)
        self.num_worlds = self.model.num_worlds
        self._nw = self.model.particles_per_world
        self._mw = self.model.meshes_per_world
        self._latch = self.robot.gripper_joint is not None and len(self._tool_mesh) == 2

        # Gaussians: [background | robot | objects... | colliders...] in one buffer per state (the background
        # in spatial order: the renderer culls runs of it at once, see RenderCache.balls)
        background = with_color_map(spec.background, spec.background_color_map)
        static = [] if background is None else [background.spatially_sorted()]
        self.robot_gaussians = _robot_gaussians(spec.robot, self.robot)
        # the leading run of robot Gaussians (sorted by link, root first) on links that never move (the base)
        # is stored posed, once: it joins the static scene, and the poser moves only the rest
        rg = self.robot_gaussians
        on_fixed = self.robot.fixed_links[rg.link_index]
        n_fixed = len(rg) if on_fixed.all() else int(np.argmin(on_fixed))
        fixed = rg.posed(self.robot.home_q).subset(slice(0, n_fixed))
        moving_robot = rg.local.subset(slice(n_fixed, len(rg)))
        parts = static + [fixed, moving_robot]
        n_static = sum(len(g) for g in static) + n_fixed
        offset = n_static + len(moving_robot)
        self._objects: dict[str, _ObjectSlot] = {}
        self._posers: dict[str, LabelRigidPoser | LBSSkinner] = {}
        for obj, p_start in slots:
            rest = obj.rest_gaussians
            count = 0 if rest is None else len(rest)
            self._objects[obj.name] = _ObjectSlot(
                obj.name,
                p_start,
                obj.num_particles,
                offset,
                count,
                np.asarray(obj.particles, np.float64),
                obj.rest_pose,
            )
            if rest is not None:
                parts.append(rest)
                if obj.binding == "rigid":
                    self._posers[obj.name] = LabelRigidPoser(rest, np.zeros(count, np.int32), 1, device)
                else:
                    binding = bind(rest.means, obj.particles, device=device)
                    self._posers[obj.name] = LBSSkinner(binding, rest.means, rest.quats, device)
            offset += count
        self._colliders: dict[str, tuple[int, int]] = {}  # name -> (first Gaussian, count)
        for col in spec.colliders:
            rest = with_color_map(col.gaussians, col.color_map)
            if rest is not None:
                parts.append(rest)
                self._colliders[col.name] = (offset, len(rest))
                self._posers[col.name] = LabelRigidPoser(rest, np.zeros(len(rest), np.int32), 1, device)
                offset += len(rest)
        self._rest_gaussians = GaussianCloud.concatenate(parts)
        self._robot_range = (n_static, len(moving_robot))  # the robot's moving Gaussians
        self._robot_poser = rg.device_poser(device, first=n_fixed) if len(moving_robot) else None
        # the static scene's per-camera render work, kept while a camera does not move (None: full renders;
        # the default on CUDA, where a full render of a batch costs about what a cached one does)
        self.render_cache: RenderCache | None = RenderCache() if wp.get_device(device).is_cpu else None
        self._static_gaussians: DeviceGaussians | None = None  # background + fixed links, every world's

    # ------------------------------------------------------------------ state
    @property
    def object_names(self) -> list[str]:
        return list(self._objects)

    @property
    def collider_names(self) -> list[str]:
        return [c.name for c in self.spec.colliders]

    def new_state(self) -> TwinState:
        """A state with the robot at home and every object at its rest pose (a one-world twin)."""
        if self.num_worlds != 1:
            raise ValueError(f"this twin has {self.num_worlds} worlds: use new_states()")
        return self.new_states()[0]

    def new_states(self) -> list[TwinState]:
        """One state per world over fresh shared physics buffers, each world reset to home and rest."""
        physics, control, posed = self.model.state(), self.model.control(), _PosedGaussians()
        states = [
            TwinState(physics=physics, control=control, robot=self.controller.initial_state(), world=w,
                      posed=posed)
            for w in range(self.num_worlds)
        ]
        for state in states:
            self.reset(state)
        return states

    def _mesh(self, state: TwinState, mid: int) -> int:
        return mid + state.world * self._mw

    def _span(self, state: TwinState, start: int = 0, count: int | None = None) -> slice:
        base = state.world * self._nw + start
        return slice(base, base + (self._nw if count is None else count))

    def reset(
        self,
        state: TwinState,
        q0: np.ndarray | None = None,
        object_poses: dict[str, np.ndarray] | None = None,
    ) -> None:
        """Robot at q0 (default home), each object at rest at its pose and each collider at its pose
        (`object_poses` keyed by object or collider name; default: their poses in the spec)."""
        state.robot = self.controller.initial_state(q0)
        poses = dict(object_poses or {})
        unknown = set(poses) - set(self._objects) - set(self._collider_mesh)
        if unknown:
            raise ValueError(
                f"object_poses: unknown objects {sorted(unknown)}; objects: {self.object_names}, "
                f"colliders: {self.collider_names}"
            )
        x = self.model.x0_np[: self._nw].copy()
        state.object_poses = {}
        for name, slot in self._objects.items():
            pose = np.asarray(poses.get(name, slot.rest_pose), dtype=np.float64)
            if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
                raise ValueError(
                    f"object_poses[{name!r}]: expected a finite 4x4 pose, got shape {pose.shape}"
                )
            x[slot.start : slot.start + slot.count] = transform_points(pose, slot.rest_particles)
            state.object_poses[name] = pose.copy()
        span = self._span(state)
        state.physics.x[span].assign(x.astype(np.float32))
        state.physics.v[span].zero_()
        self._hold_tools(state)
        for col in self.spec.colliders:
            pose = np.asarray(poses.get(col.name, col.pose), dtype=np.float64)
            if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
                raise ValueError(
                    f"object_poses[{col.name!r}]: expected a finite 4x4 pose, got shape {pose.shape}"
                )
            verts = transform_points(pose, col.vertices)
            state.control.set_kinematic_mesh(self._mesh(state, self._collider_mesh[col.name]), verts, verts)
            state.collider_poses[col.name] = pose.copy()
        state.frame = 0
        state.finger_forces = None
        state.command = None
        self._fit_poses(state)

    # ------------------------------------------------------------------ dynamics
    def step(self, state: TwinState, action) -> RobotCommand:
        """One control step (30 Hz frame) of a one-world twin. Raises `SimulationDiverged` when the
        simulation blows up, `ValueError` for a malformed action."""
        if self.num_worlds != 1:
            raise ValueError(f"this twin has {self.num_worlds} worlds: use step_worlds(states, actions)")
        (result,) = self.step_worlds([state], [action])
        if isinstance(result, SimulationDiverged):
            raise result
        return result

    def step_worlds(self, states: list[TwinState], actions: list) -> list[RobotCommand | SimulationDiverged]:
        """One control step of every world in one physics frame. `states` are this twin's worlds in order
        (`new_states()`); `actions[w]` is world w's action, or None to hold its robot still (an idle
        world). Returns per world its RobotCommand, None when held, or the `SimulationDiverged` that
        ended it (the other worlds go on; a diverged world stays diverged until it is reset). A malformed
        action raises `ValueError` before anything moves."""
        if [s.world for s in states] != list(range(self.num_worlds)) or any(
            s.physics is not states[0].physics for s in states
        ):
            raise ValueError(f"step_worlds needs this twin's {self.num_worlds} world states in order "
                             "(from new_states())")
        if len(actions) != len(states):
            raise ValueError(f"step_worlds: {len(actions)} actions for {len(states)} worlds")
        moving = [i for i, a in enumerate(actions) if a is not None]
        cmds: list = [None] * len(states)
        if moving:  # one batched IK solve for every moving world
            done = self.controller.advance_worlds(
                [states[i].robot for i in moving], [actions[i] for i in moving],
                [states[i].finger_forces for i in moving],
            )
            for i, cmd in zip(moving, done, strict=True):
                cmds[i] = cmd
        for state, cmd in zip(states, cmds, strict=True):
            if cmd is None:
                self._hold_tools(state)
            else:
                frames = self.robot.contact_mesh_frames(cmd.q_prev, cmd.q)
                for link, mid in self._tool_mesh.items():
                    state.control.set_kinematic_mesh(self._mesh(state, mid), *frames[link])
        self.solver.simulate_frame(states[0].physics, states[0].control, check=False)
        bad = check_divergence(states[0].physics, self.solver.max_speed)
        bad_world = bad // self._nw
        x = states[0].physics.x.numpy()
        results: list = []
        for state, cmd in zip(states, cmds, strict=True):
            mine = bad[bad_world == state.world]
            if mine.size:
                results.append(SimulationDiverged(mine - state.world * self._nw))
                continue
            results.append(cmd)
            if cmd is None:
                continue
            if self._latch:  # the fingers' contact force magnitudes, for the latch on the next step
                left, right = (
                    float(np.linalg.norm(self.solver.mesh_contact_force(self._mesh(state, m))))
                    for m in self._tool_mesh.values()
                )
                state.finger_forces = (left, right)
            state.command = cmd
            state.frame += 1
            self._fit_poses(state, x)
        return results

    def _hold_tools(self, state: TwinState) -> None:
        """Tool meshes still at the state's robot configuration for the next frame."""
        for link, mid in self._tool_mesh.items():
            verts = self.robot.contact_vertices(state.robot.q, link)
            state.control.set_kinematic_mesh(self._mesh(state, mid), verts, verts)

    def _fit_poses(self, state: TwinState, x: np.ndarray | None = None) -> None:
        x = (state.physics.x.numpy() if x is None else x)[self._span(state)]
        for name, slot in self._objects.items():
            state.object_poses[name] = fit_rigid_transform(
                slot.rest_particles, x[slot.start : slot.start + slot.count]
            )

    # ------------------------------------------------------------------ queries
    def particles(self, state: TwinState, name: str) -> np.ndarray:
        """Current world positions (P, 3) of an object's particles (a copy)."""
        slot = self._slot(name)
        return state.physics.x[self._span(state, slot.start, slot.count)].numpy().copy()

    def object_springs(self, name: str) -> np.ndarray:
        """(M, 2) springs of an object, as indices into its own particles."""
        slot = self._slot(name)
        s = self.model.springs_np[: self.model.num_object_springs // self.num_worlds]  # world 0's
        mine = (s[:, 0] >= slot.start) & (s[:, 0] < slot.start + slot.count)
        return (s[mine] - slot.start).astype(np.int64)

    def rest_particles(self, name: str) -> np.ndarray:
        """An object's particles in its own frame (P, 3)."""
        return self._slot(name).rest_particles.copy()

    def collider_pose(self, state: TwinState, name: str) -> np.ndarray:
        """A collider's pose (4x4) in this episode."""
        if name not in self._collider_mesh:
            raise KeyError(
                f"twin {self.spec.name!r} has no collider {name!r}; colliders: {self.collider_names}"
            )
        return state.collider_poses[name].copy()

    def object_pose(self, state: TwinState, name: str) -> np.ndarray:
        """Best-fit rigid pose (4x4) of an object's particles relative to its object frame."""
        self._slot(name)
        return state.object_poses[name].copy()

    def grasp_status(self, state: TwinState) -> str | None:
        """For a gripper: "holding" (both fingers in contact, over 5 % of the latch force), "closed_on_air"
        (fully closed without contact), "closing", or "open"; None without a gripper."""
        if not self._latch:
            return None
        threshold = self.controller.config.grasp_force_threshold
        forces = state.finger_forces or (0.0, 0.0)
        if min(forces) > 0.05 * threshold:
            return "holding"
        g = state.robot.gripper
        return "closed_on_air" if g >= 0.99 else ("closing" if g > 0.0 else "open")

    def ee_state(self, state: TwinState) -> np.ndarray:
        """The policy's state vector (see ControllerConfig.action_mode)."""
        return self.controller.ee_state(state.robot)

    def _slot(self, name: str) -> _ObjectSlot:
        if name not in self._objects:
            raise KeyError(f"twin {self.spec.name!r} has no object {name!r}; objects: {self.object_names}")
        return self._objects[name]

    # ------------------------------------------------------------------ appearance
    def pose_gaussians(self, state: TwinState) -> DeviceGaussians:
        """Pose the state's Gaussians: robot links by FK, objects by rigid fit or LBS. Returns them."""
        return self.pose_worlds([state])[0]

    def pose_worlds(self, states: list[TwinState]) -> list[DeviceGaussians]:
        """Pose several states' Gaussians (e.g. every world's): each poser runs once for all the states
        that share buffers. Returns each state's Gaussians; each equals `pose_gaussians(state)`."""
        groups: dict[int, list[TwinState]] = {}
        for state in states:
            groups.setdefault(id(state.posed), []).append(state)
        for group in groups.values():
            self._pose_group(group)
        return [state.gaussians for state in states]

    def _pose_group(self, states: list[TwinState]) -> None:
        posed = states[0].posed
        n = len(self._rest_gaussians)
        if posed.all is None:
            rest = self._rest_gaussians.to_device(self.device)
            worlds = self.num_worlds
            posed.all = rest if worlds == 1 else DeviceGaussians.concatenate([rest] * worlds)
        for state in states:
            if state.gaussians is None:
                state.gaussians = posed.all.segment(state.world * n, n)
        first = np.array([state.world * n for state in states])
        g = posed.all
        q = np.stack([state.robot.q for state in states])
        if self._robot_poser is not None:
            self._robot_poser.update_many(self.robot.fk(q), g, first + self._robot_range[0])
        for name, poser in self._posers.items():
            if name in self._colliders:
                poses = np.stack([state.collider_poses[name] for state in states])[:, None]
                poser.update_many(poses, g, first + self._colliders[name][0])
                continue
            slot = self._objects[name]
            if isinstance(poser, LabelRigidPoser):
                poses = np.stack([state.object_poses[name] for state in states])[:, None]
                poser.update_many(poses, g, first + slot.g_start)
            else:
                particles = [state.world * self._nw + slot.start for state in states]
                poser.update_many(states[0].physics.x, particles, g.means, g.quats, first + slot.g_start)

    def camera(self, state: TwinState, name: str) -> Camera:
        """The Camera of a named camera at the state's robot configuration."""
        if name not in self.cameras:
            raise KeyError(f"twin {self.spec.name!r} has no camera {name!r}; cameras: {list(self.cameras)}")
        spec = self.cameras[name]
        pose = spec.pose
        if spec.mount_link is not None:
            pose = self.robot.link_pose(state.robot.q, spec.mount_link) @ pose
        return spec.view(pose)

    def render(self, state: TwinState, cameras: list[str] | None = None) -> dict[str, RenderOutput]:
        """Render the named cameras (default: all) -> {name: RenderOutput (rgb, depth, alpha)}."""
        return self.render_worlds([state], cameras)[0]

    def render_worlds(self, states: list[TwinState], cameras: list[str] | None = None) -> list[dict]:
        """Render the named cameras (default: all) of several states (e.g. every world) in one call
        (`render_batch`: on CPU the views are spread over the cores) -> per state {name: RenderOutput}.
        Each state's images equal `render(state)`."""
        names = list(self.cameras) if cameras is None else list(cameras)
        if not states:
            return []
        posed = self.pose_worlds(states)
        n_static, n_moving = self._robot_range[0], len(self._rest_gaussians) - self._robot_range[0]
        if self.render_cache is not None and n_static:  # [background, fixed links | the rest]: RenderCache
            if self._static_gaussians is None:
                static = self._rest_gaussians.subset(slice(0, n_static))
                self._static_gaussians = static.to_device(self.device)
            posed = [SplitGaussians(self._static_gaussians, g.segment(n_static, n_moving), g) for g in posed]
        views = [(g, self.camera(state, n)) for state, g in zip(states, posed, strict=True) for n in names]
        outs = render_batch(views, background=self.spec.render_background, device=self.device,
                            cache=self.render_cache)
        k = len(names)
        return [dict(zip(names, outs[i * k : (i + 1) * k], strict=True)) for i in range(len(states))]


def build_twin(
    spec: TwinSpec, device: str = "cpu", num_worlds: int = 1
) -> tuple[Twin, TwinState] | tuple[Twin, list[TwinState]]:
    """Build `spec` on `device` -> (Twin, its TwinState at rest), or with `num_worlds` > 1 (Twin, one
    TwinState per world) for `Twin.step_worlds`."""
    if isinstance(num_worlds, bool) or not isinstance(num_worlds, int | np.integer) or num_worlds < 1:
        raise ValueError(f"num_worlds must be a positive integer, got {num_worlds!r}")
    twin = Twin(spec, device, int(num_worlds))
    states = twin.new_states()
    return (twin, states[0]) if num_worlds == 1 else (twin, states)
