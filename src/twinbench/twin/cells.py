"""Built-in procedural cells (no download), produced as TwinSpecs like any twin loaded from disk.

The reference workcell: a procedural table and backdrop (Gaussians), the built-in xArm-7-like arm with
the reference study's cameras (`study_cameras`: its front D455 and its wrist D405 on the flange, their
intrinsics, 848x480 sensors and each task's crops), and the task's objects. Every cell has the presets
`reference` (the default) and `fast` (cheaper physics), which follow the study's layout as far as it is
public (object sizes and poses, its 20 cm pusher, the flange as the gripper tasks' end-effector frame), and
`small` / `small-fast`, the earlier scaled-down cells with their own cameras, tools and frames. The study's
scanned rope, clip, sloth and box are not public: here they are procedural stand-ins of their sizes (and,
for the sloth, its particle count).

- `push_t_cell(preset)`: the arm with a vertical pusher held at a fixed height above the table (its
  radius is the robot's `tool_radius`), and a T-block made of particles (volume lattice, springs within a
  radius, max 50 neighbours, uniform Y = 3e4) whose coloured surface Gaussians follow its rigid motion;
  the T's outline is the object's `outline` (`block_scale` scales the T, its lattice and its Y). Presets:
  `reference` (5 mm lattice, 667 substeps per 30 Hz frame, PhysTwin's dt = 5e-5 s) and `fast` (15 mm
  lattice, 100 substeps, about 50x cheaper; the demo and the tests use it): the study's 15 x 15 cm T, its
  start and goal poses; `small` / `small-fast`: a 12 x 12 cm T resting at (0.5, 0) as its own goal.
- `rope_routing_cell(preset)`: the arm with its parallel gripper (friction on the finger pads, the force
  latch of DESIGN §5), a 32 cm cotton-like rope (a 1 cm thick cylinder of particles, springs within a
  radius; its marked end is red) lying on the table, and a clip: two walls on the table forming a channel
  along y with an opening at each end (the collider's `channel`): the study's 3.5 x 3 x 3.5 cm success box
  at (0.62, 0.05) in `reference`/`fast` (`STUDY_ROPE`), a 2 x 3 x 4 cm channel at (0.45, 0.12) in the small
  cells.
- `toy_packing_cell(preset)`: the gripper arm, a plush toy (a torso and four softer limbs) and an open box:
  the study's sizes in `reference`/`fast` (`STUDY_TOY`), a 7 x 5 x 4 cm toy and a 9 x 7.5 x 7 cm box in
  the small cells.
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

import numpy as np

from twinbench.gaussians.camera import look_at_pose
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.physics import SimParams
from twinbench.robot.builtin import PUSHERS
from twinbench.robot.controller import ControllerConfig
from twinbench.transforms import planar_pose
from twinbench.twin.assets import (
    backdrop_gaussians,
    box_mesh,
    mesh_surface_gaussians,
    paint,
    table_gaussians,
)
from twinbench.twin.shapes import TBlockShape, sample_block_particles
from twinbench.twin.spec import CameraSpec, ColliderSpec, ContactSpec, ObjectSpec, RobotSpec, TwinSpec

# (fx, fy, cx, cy) of the reference cell's cameras (DESIGN §5); both sensors are 848x480.
FRONT_INTRINSICS = (427.29, 426.79, 430.00, 242.81)
WRIST_INTRINSICS = (433.26, 433.26, 425.70, 244.70)
STUDY_FRONT_K = (427.2920227050781, 426.7926940917969, 429.9993591308594, 242.8115234375)
STUDY_WRIST_K = (433.2635498046875, 433.2635498046875, 425.69775390625, 244.70132446289062)


def front_camera(output_hw=(240, 240), eye=(0.92, -0.42, 0.52), target=(0.46, 0.0, 0.0)) -> CameraSpec:
    """The fixed external camera: front-left of the table, looking down at the workspace."""
    return CameraSpec("front", FRONT_INTRINSICS, look_at_pose(eye, target), output_hw=tuple(output_hw))


def wrist_camera(
    mount_link: str = "link7", output_hw=(240, 240), offset=(0.0, -0.12, 0.05), look=(0.0, 0.0, 0.2)
) -> CameraSpec:
    """A camera fixed to `mount_link` at `offset` (link frame) looking at `look` (link frame): with the
    built-in arm's flange frame (z along the tool), past the tool tip."""
    return CameraSpec(
        "wrist",
        WRIST_INTRINSICS,
        look_at_pose(offset, look, up=(1.0, 0.0, 0.0)),
        mount_link=mount_link,
        output_hw=tuple(output_hw),
    )


# The reference study's cameras (kywind/real2sim-eval cfg/env/xarm_*.yaml): a D455 in front of the table
# (camera-to-world, OpenCV axes) and a D405 on the flange (`link_eef` = the built-in arm's link7 frame),
# both 848x480.
STUDY_FRONT_POSE = np.array([
    [0.005258014128948334, 0.6125512321694572, -0.7904133989597472, 0.8830263898083726],
    [0.9999860093046595, -0.0036779908994199082, 0.0038017861441641317, 0.05390846195611962],
    [-0.000578344501100992, -0.7904223303719503, -0.6125620010799026, 0.3976033855145515],
    [0.0, 0.0, 0.0, 1.0],
])
STUDY_WRIST_POSE = np.array([
    [-0.00621799798682332, -0.9996882472848673, -0.024181019135736517, 0.070151686668396],
    [0.9999282360076904, -0.0059682438456119995, -0.010387018683749047, -0.006011864222586155],
    [0.01023946, -0.02424387, 0.99965361, 0.03072427],
    [0.0, 0.0, 0.0, 1.0],
])


def study_cameras(front_crop, wrist_crop, output_hw) -> tuple[CameraSpec, CameraSpec]:
    """The reference study's front and wrist cameras with a task's crops ((x0, y0, w, h) sensor pixels)
    resized to `output_hw`. The wrist pose is orthonormalised (the study's matrix is rounded)."""
    u, _, vt = np.linalg.svd(STUDY_WRIST_POSE[:3, :3])
    wrist = STUDY_WRIST_POSE.copy()
    wrist[:3, :3] = u @ vt
    return (
        CameraSpec("front", STUDY_FRONT_K, STUDY_FRONT_POSE, crop=tuple(front_crop),
                   output_hw=tuple(output_hw)),
        CameraSpec("wrist", STUDY_WRIST_K, wrist, mount_link="link7", crop=tuple(wrist_crop),
                   output_hw=tuple(output_hw)),
    )


def workcell_background() -> GaussianCloud:
    """The procedural table (z = 0) and the wall behind the robot."""
    return GaussianCloud.concatenate([table_gaussians(), backdrop_gaussians()])


@dataclass(frozen=True)
class PushTCell:
    """Settings of the built-in push-T cell. `PushTCell.preset(name, **overrides)` gives the presets."""

    particle_spacing: float = 0.005  # m, T-block lattice
    spring_radius_factor: float = 1.9  # springs within this many lattice spacings
    substeps: int = 667  # per 30 Hz frame
    fps: float = 30.0
    image_hw: tuple[int, int] = (240, 240)
    block_pose: tuple[float, float, float] = (0.5, 0.0, 0.0)  # x, y, theta of the T at rest (= the goal)
    pusher_height: float = 0.01  # m, pusher tip above the table
    ground_friction: float = 0.5
    pusher_friction: float = 0.3
    robot_gaussian_spacing: float = 0.006
    block_scale: float = 1.0  # the T's size, lattice spacing and spring Y relative to `t_shape`
    # the T: bar length, bar width, stem length, stem width, height (m)
    t_shape: tuple[float, ...] = (0.12, 0.03, 0.09, 0.03, 0.03)
    goal_pose: tuple[float, float, float] | None = None  # x, y, theta of the goal; None: the rest pose
    study_cameras: bool = False  # the reference study's cameras and push-T crops (else the small cell's)
    pusher: str = "pusher"  # the built-in pusher tool: "pusher" (15 mm rod) or "pusher20" (the study's)

    @staticmethod
    def preset(name: str, **overrides) -> PushTCell:
        study = PushTCell(**STUDY_PUSH_T)
        presets = {
            "reference": study,
            "fast": replace(study, particle_spacing=0.015, substeps=100),
            "small": PushTCell(),
            "small-fast": PushTCell(particle_spacing=0.015, substeps=100),
        }
        return _check_settings(PushTCell, "push-t", presets, name, overrides)


# The reference study's push-T (kywind/real2sim-eval): the T measured from the particles of its goal
# (experiments/utils/T_final_state.pkl: bar 15 x 4 cm, stem 11 x 4 cm, 3 cm high; their area centroid at
# (0.4193, 0.0015), stem toward the robot, i.e. the bar along -y), the start pose of cfg/gs/T.yaml (the T at
# x = 0.43 turned by -90 deg), its 20 cm pusher (a 10.2 mm rod, tip 21.5 cm below the flange) with the tip
# 5 mm above the table (flange at z = 0.22).
STUDY_PUSH_T = dict(
    pusher="pusher20",
    t_shape=(0.15, 0.04, 0.11, 0.04, 0.03),
    block_pose=(0.43, 0.0, -np.pi / 2),
    goal_pose=(0.4193, 0.0015, -np.pi / 2 - 0.0034),
    pusher_height=0.005,
    study_cameras=True,
)
PUSH_T_FRONT_CROP = (184, 100, 440, 280)  # x0, y0, w, h: the study's rows 100-380, cols 184-624
PUSH_T_WRIST_CROP = (184, 0, 480, 480)  # cols 184-664


def push_t_cell(preset: str = "reference", **overrides) -> TwinSpec:
    """The built-in push-T twin (see the module docstring)."""
    cfg = PushTCell.preset(preset, **overrides)
    if not cfg.block_scale > 0:
        raise ValueError(f"push-t cell: block_scale must be > 0, got {cfg.block_scale}")
    shape = TBlockShape(*cfg.t_shape).scaled(cfg.block_scale)
    spacing = cfg.particle_spacing * cfg.block_scale
    block = ObjectSpec(
        "tblock",
        sample_block_particles(shape, spacing),
        spring_Y=3e4 * cfg.block_scale,  # the springs' stiffness Y / rest length stays the reference's
        spring_radius=cfg.spring_radius_factor * spacing,
        max_neighbors=50,
        gaussians=mesh_surface_gaussians(shape.mesh(), (0.30, 0.42, 0.68)),
        binding="rigid",
        rest_pose=planar_pose(*cfg.block_pose),
        outline=shape.outline(),
        goal_pose=None if cfg.goal_pose is None else planar_pose(*cfg.goal_pose),
    )
    sim = SimParams(
        dt=1.0 / cfg.fps / cfg.substeps,
        substeps=cfg.substeps,
        ground_restitution=0.0,
        ground_friction=cfg.ground_friction,
        object_collision=False,
        mesh_margin=0.6 * spacing,
    )
    if cfg.pusher not in PUSHERS:
        raise ValueError(f"push-t cell: pusher must be one of {sorted(PUSHERS)}, got {cfg.pusher!r}")
    robot = RobotSpec(
        f"builtin:xarm7_{cfg.pusher}",
        scan_spacing=cfg.robot_gaussian_spacing,
        tool_contact=ContactSpec(0.0, cfg.pusher_friction),
        tool_radius=PUSHERS[cfg.pusher][0],
    )
    return TwinSpec(
        name=f"push-t-{preset}",
        robot=robot,
        objects=(block,),
        cameras=study_cameras(PUSH_T_FRONT_CROP, PUSH_T_WRIST_CROP, cfg.image_hw)
        if cfg.study_cameras
        else (front_camera(cfg.image_hw), wrist_camera("link7", cfg.image_hw)),
        background=workcell_background(),
        sim=sim,
        controller=ControllerConfig(action_mode="planar", planar_height=cfg.pusher_height),
    )


def _check_settings(cls, name: str, presets: dict, preset: str, overrides: dict):
    """The named preset of a cell's settings with `overrides` applied; errors name what is allowed."""
    if preset not in presets:
        raise ValueError(f"{name} preset must be one of {sorted(presets)}, got {preset!r}")
    known = {f.name for f in fields(cls)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"{name} cell: unknown setting(s) {unknown}; known: {sorted(known)}")
    return replace(presets[preset], **overrides)


EE_FRAMES = {"flange": "link7", "tool": "tcp"}  # a gripper cell's `ee_frame` -> RobotSpec.ee_link


def gripper_robot(finger_friction: float = 1.0, scan_spacing: float = 0.006, ee_frame: str = "tool"
                  ) -> RobotSpec:
    """The built-in arm with its parallel gripper; finger pads with friction `finger_friction`. `ee_frame`:
    the frame of the policy's state and actions, "flange" (the reference study's `link_eef`) or "tool"
    (the `tcp` point 13 cm below it, 15 mm above the fingertips)."""
    if ee_frame not in EE_FRAMES:
        raise ValueError(f"ee_frame must be one of {sorted(EE_FRAMES)}, got {ee_frame!r}")
    return RobotSpec(
        "builtin:xarm7_gripper",
        ee_link=EE_FRAMES[ee_frame],
        scan_spacing=scan_spacing,
        tool_contact=ContactSpec(0.0, finger_friction),
    )


# ----------------------------------------------------------------------------------------------- rope
ROPE_RGB, MARK_RGB, CLIP_RGB = (0.86, 0.80, 0.66), (0.85, 0.12, 0.10), (0.15, 0.45, 0.30)


@dataclass(frozen=True)
class RopeCell:
    """Settings of the built-in rope-routing cell. `RopeCell.preset(name, **overrides)` gives the presets."""

    length: float = 0.32  # m
    axial_spacing: float = 0.004  # m between particle rings along the rope
    ring: int = 9  # particles per cross-section: 5 (centre + 4) or n * n (a square grid, n >= 2)
    radius: float = 0.005  # m, half the rope's thickness
    spring_Y: float = 1e4
    spring_radius: float | None = None  # m, springs within it; None: 1.3 x the larger lattice spacing
    max_neighbors: int = 30
    substeps: int = 667
    rope_pose: tuple[float, float, float] = (0.45, -0.12, 1.5707963267948966)  # x, y, theta: along +y
    clip_pose: tuple[float, float, float] = (0.45, 0.12, 0.0)  # channel along the clip frame's y
    clip_yaw: float = 0.0  # rad, the clip's walls turned about the channel's centre (the frame is not)
    channel_width: float = 0.02
    channel_depth: float = 0.03
    channel_length: float = 0.04
    wall_thickness: float = 0.012
    finger_friction: float = 1.0
    ground_friction: float = 0.6
    self_collision: bool = True
    image_hw: tuple[int, int] = (240, 240)
    robot_gaussian_spacing: float = 0.006
    study_cameras: bool = False  # the reference study's cameras, full 848x480 frames (else the small cell's)
    ee_frame: str = "tool"  # state and actions of the "flange" (the study's) or the "tool" point

    @staticmethod
    def preset(name: str, **overrides) -> RopeCell:
        small = RopeCell()
        small_fast = RopeCell(axial_spacing=0.006, ring=5, substeps=150, self_collision=False)
        presets = {
            "reference": replace(small, **STUDY_ROPE),
            "fast": replace(small, **{**STUDY_ROPE, **STUDY_ROPE_FAST}),
            "small": small,
            "small-fast": small_fast,
        }
        return _check_settings(RopeCell, "rope-routing", presets, name, overrides)


ROPE_CROP = (0, 0, 848, 480)  # the study's rope policy: the full frame resized to 120 x 212
ROPE_IMAGE_HW = (120, 212)
# The reference study's rope routing (kywind/real2sim-eval cfg/gs/rope.yaml, calculate_success_rope.py): its
# clip at (0.62, 0.05) turned -2 deg, its success box 3.5 x 3.5 x 3 cm (x, y, z) around (0.62, 0.05), on the
# table and aligned with the world axes, whose y faces are the openings; the rope's origin at (0.36, 0). The
# clip frame here is that box (the channel = the box; the stand-in clip's walls are turned -2 deg in it), and
# the rope is denser than the small cell's so that the study's 100 crossing springs per opening can be reached
# (reference: a 4 x 4 section every 4 mm, springs within 8 mm, 204 springs cross a section of the straight
# rope; fast: every 6 mm, springs within 9 mm, 180; springs reach 2 and 1.5 sections: the rope still bends).
STUDY_ROPE = dict(
    ring=16,
    spring_radius=0.008,
    max_neighbors=40,
    rope_pose=(0.36, 0.0, 0.0),
    clip_pose=(0.62, 0.05, 0.0),
    clip_yaw=float(np.deg2rad(-2.0)),
    channel_width=0.035,
    channel_length=0.035,
    study_cameras=True,
    image_hw=ROPE_IMAGE_HW,
    ee_frame="flange",
)
STUDY_ROPE_FAST = dict(axial_spacing=0.006, spring_radius=0.009, max_neighbors=50, substeps=150,
                       self_collision=False)


def rope_particles(length: float, axial_spacing: float, ring: int, radius: float) -> np.ndarray:
    """(P, 3) particles of a straight rope along x in its own frame (centred, lying on z = 0): rings of
    `ring` particles (5: centre and 4 at 0.8 radius; n * n: a square grid spanning +-0.8 radius) every
    `axial_spacing` metres."""
    side = int(round(np.sqrt(ring)))
    if ring != 5 and (side < 2 or side * side != ring):
        raise ValueError(f"ring must be 5 or a square n * n >= 4 (9, 16, ...), got {ring}")
    n = int(round(length / axial_spacing)) + 1
    d = 0.8 * radius
    if ring == 5:
        section = [(0, 0), (d, 0), (-d, 0), (0, d), (0, -d)]
    else:
        grid = np.linspace(-d, d, side)
        section = [(a, b) for a in grid for b in grid]
    xs = np.linspace(-length / 2, length / 2, n)
    return np.array([(x, y, radius + z) for x in xs for (y, z) in section])


def rope_routing_cell(preset: str = "reference", **overrides) -> TwinSpec:
    """The built-in rope-routing twin (see the module docstring)."""
    import trimesh

    cfg = RopeCell.preset(preset, **overrides)
    pts = rope_particles(cfg.length, cfg.axial_spacing, cfg.ring, cfg.radius)
    tube = trimesh.creation.cylinder(radius=cfg.radius, height=cfg.length, sections=12)
    tube.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (0, 1, 0)))
    tube.apply_translation((0, 0, cfg.radius))
    skin = mesh_surface_gaussians(tube, ROPE_RGB, spacing=0.0025)
    skin = paint(skin, skin.means[:, 0] > cfg.length / 2 - 0.03, MARK_RGB)  # the marked end (+x)
    spacing = cfg.axial_spacing
    rope = ObjectSpec(
        "rope",
        pts,
        spring_Y=cfg.spring_Y,
        spring_radius=cfg.spring_radius or 1.3 * max(spacing, 0.8 * cfg.radius * 1.42),
        max_neighbors=cfg.max_neighbors,
        gaussians=skin,
        binding="lbs",
        rest_pose=planar_pose(*cfg.rope_pose),
    )
    w, depth, half_len, t = (
        cfg.channel_width / 2,
        cfg.channel_depth,
        cfg.channel_length / 2,
        cfg.wall_thickness,
    )
    walls = [
        box_mesh((-w - t, -half_len, 0.0), (-w, half_len, depth)),
        box_mesh((w, -half_len, 0.0), (w + t, half_len, depth)),
    ]
    clip_mesh = trimesh.util.concatenate(walls)
    clip_mesh.apply_transform(trimesh.transformations.rotation_matrix(cfg.clip_yaw, (0, 0, 1)))
    clip = ColliderSpec(
        "clip",
        np.asarray(clip_mesh.vertices),
        np.asarray(clip_mesh.faces),
        planar_pose(*cfg.clip_pose),
        ContactSpec(0.0, 0.5),
        mesh_surface_gaussians(clip_mesh, CLIP_RGB, spacing=0.003),
        channel=(cfg.channel_width, cfg.channel_depth, cfg.channel_length),
    )
    dt = 1.0 / 30.0 / cfg.substeps
    sim = SimParams(
        dt=dt,
        substeps=cfg.substeps,
        ground_restitution=0.0,
        ground_friction=cfg.ground_friction,
        object_collision=False,
        self_collision=cfg.self_collision,
        collision_dist=0.6 * spacing,
        candidate_radius_scale=2.0,
        mesh_margin=0.002,
    )
    return TwinSpec(
        name=f"rope-routing-{preset}",
        robot=gripper_robot(cfg.finger_friction, cfg.robot_gaussian_spacing, cfg.ee_frame),
        objects=(rope,),
        colliders=(clip,),
        cameras=study_cameras(ROPE_CROP, ROPE_CROP, cfg.image_hw)
        if cfg.study_cameras
        else (front_camera(cfg.image_hw), wrist_camera("link7", cfg.image_hw)),
        background=workcell_background(),
        sim=sim,
    )


# ----------------------------------------------------------------------------------------------- toy
TOY_RGB, LIMB_RGB, BOX_RGB = (0.93, 0.62, 0.20), (0.55, 0.33, 0.15), (0.75, 0.68, 0.52)


@dataclass(frozen=True)
class ToyCell:
    """Settings of the built-in toy-packing cell. `ToyCell.preset(name, **overrides)` gives the presets."""

    spacing: float = 0.004  # m, particle lattice of the plush toy
    particles: int | None = None  # keep this many (the torso's top corners go first); None: the lattice's
    torso: tuple[float, float, float] = (0.07, 0.05, 0.04)  # m, x y z extents
    limb_length: float = 0.04  # m, four limbs sticking out along +-y
    limb_radius: float = 0.011
    torso_Y: float = 2e4
    limb_Y: float = 800.0  # limbs are much softer (they fold when the toy is pushed into the box)
    substeps: int = 667
    toy_pose: tuple[float, float, float] = (0.40, -0.15, 0.0)
    box_pose: tuple[float, float, float] = (0.45, 0.12, 0.0)
    box_inner: tuple[float, float, float] = (0.09, 0.075, 0.07)  # m, inside of the open-top box
    wall_thickness: float = 0.01
    finger_friction: float = 1.0
    ground_friction: float = 0.6
    image_hw: tuple[int, int] = (240, 240)
    robot_gaussian_spacing: float = 0.006
    study_cameras: bool = False  # the reference study's cameras and toy crops (else the small cell's)
    ee_frame: str = "tool"  # state and actions of the "flange" (the study's) or the "tool" point

    @staticmethod
    def preset(name: str, **overrides) -> ToyCell:
        small, small_fast = ToyCell(), ToyCell(spacing=0.008, substeps=150)
        presets = {
            "reference": replace(small, **STUDY_TOY),
            "fast": replace(small_fast, **{**STUDY_TOY, "spacing": small_fast.spacing, "particles": None}),
            "small": small,
            "small-fast": small_fast,
        }
        return _check_settings(ToyCell, "toy-packing", presets, name, overrides)


TOY_CROP = (100, 0, 648, 480)  # the study's sloth policy: cols 100-748, resized to 240 x 240
# The reference study's toy packing (kywind/real2sim-eval cfg/gs/sloth.yaml, calculate_success_sloth.py): a
# scanned plush sloth of 3,095 particles at (0.5, -0.17) and a scanned box at (0.45, 0.18) whose minimal
# oriented bounding box is 0.2 x 0.13 x 0.27 m. Neither scan is public: the stand-ins are a procedural plush
# (a 10 x 6 x 5 cm torso, four 5 cm limbs, 16 cm across; 3,095 particles in `reference`, the 8 mm lattice's
# in `fast`) and an open box of 0.2 (x) x 0.27 (y) x 0.13 (z) m outside (which extent is the height is our
# reading: 13 cm).
STUDY_TOY = dict(
    spacing=0.0052,
    particles=3095,
    torso=(0.10, 0.06, 0.05),
    limb_length=0.05,
    limb_radius=0.014,
    toy_pose=(0.5, -0.17, 0.0),
    box_pose=(0.45, 0.18, 0.0),
    box_inner=(0.18, 0.25, 0.13),
    study_cameras=True,
    ee_frame="flange",
)


def toy_particles(cfg: ToyCell) -> tuple[np.ndarray, np.ndarray]:
    """(P, 3) particles of the plush toy in its own frame (torso centred above the origin, on z = 0) and a
    (P,) bool mask of the limb particles: a lattice clipped to a box torso and four cylindrical limbs along
    +-y at x = +-(torso x / 3), at mid height."""
    s = cfg.spacing
    tx, ty, tz = cfg.torso
    reach = ty / 2 + cfg.limb_length

    def centred(extent: float) -> np.ndarray:  # lattice coordinates spanning `extent`, centred on 0
        a = np.arange(0.0, extent + 1e-9, s)
        return a - a[-1] / 2

    axes = (centred(tx), centred(2 * reach), centred(tz) + tz / 2)
    g = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    torso = (np.abs(g[:, 0]) <= tx / 2 + 1e-9) & (np.abs(g[:, 1]) <= ty / 2 + 1e-9)
    limb = np.zeros(len(g), bool)
    for cx in (-tx / 3, tx / 3):
        r = np.hypot(g[:, 0] - cx, g[:, 2] - tz / 2)
        limb |= (
            (r <= cfg.limb_radius + 1e-9)
            & (np.abs(g[:, 1]) > ty / 2 + 1e-9)
            & (np.abs(g[:, 1]) <= reach + 1e-9)
        )
    keep = torso | limb
    pts, limb = g[keep], limb[keep]
    if cfg.particles is not None:
        extra = len(pts) - cfg.particles
        if extra < 0:
            raise ValueError(f"toy-packing cell: the lattice has {len(pts)} particles, fewer than "
                             f"particles={cfg.particles}; use a smaller spacing")
        # the torso's top layer, corners (farthest from the torso's axis) first
        top = np.flatnonzero(~limb & (pts[:, 2] > pts[:, 2].max() - 1e-9))
        if extra > len(top):
            raise ValueError(f"toy-packing cell: {len(pts)} lattice particles, {extra} too many for "
                             f"particles={cfg.particles}; use a larger spacing")
        order = top[np.lexsort((top, -np.hypot(pts[top, 0], pts[top, 1])))]
        drop = np.zeros(len(pts), bool)
        drop[order[:extra]] = True
        pts, limb = pts[~drop], limb[~drop]
    return pts, limb


def toy_packing_cell(preset: str = "reference", **overrides) -> TwinSpec:
    """The built-in toy-packing twin: the gripper arm, a plush toy (a torso and four softer limbs, LBS
    Gaussians) and an open-top box (a static collider of four walls) that the toy only fits in with its
    limbs tucked."""
    import trimesh

    from twinbench.physics.model import radius_springs

    cfg = ToyCell.preset(preset, **overrides)
    pts, limb = toy_particles(cfg)
    radius = 1.8 * cfg.spacing
    springs = radius_springs(pts, radius, 30)
    y = np.where(limb[springs[:, 0]] | limb[springs[:, 1]], cfg.limb_Y, cfg.torso_Y)
    parts = [
        trimesh.creation.box(
            extents=cfg.torso, transform=trimesh.transformations.translation_matrix((0, 0, cfg.torso[2] / 2))
        )
    ]
    for cx in (-cfg.torso[0] / 3, cfg.torso[0] / 3):
        for sy in (-1, 1):
            y0, y1 = sy * cfg.torso[1] / 2, sy * (cfg.torso[1] / 2 + cfg.limb_length)
            parts.append(
                trimesh.creation.cylinder(
                    radius=cfg.limb_radius, segment=((cx, y0, cfg.torso[2] / 2), (cx, y1, cfg.torso[2] / 2))
                )
            )
    skin = mesh_surface_gaussians(trimesh.util.concatenate(parts), TOY_RGB, spacing=0.003)
    skin = paint(skin, np.abs(skin.means[:, 1]) > cfg.torso[1] / 2 + 0.002, LIMB_RGB)
    toy = ObjectSpec(
        "toy",
        pts,
        springs=springs,
        spring_Y=y,
        gaussians=skin,
        binding="lbs",
        rest_pose=planar_pose(*cfg.toy_pose),
    )
    ix, iy, h = cfg.box_inner
    t = cfg.wall_thickness
    walls = [
        box_mesh((-ix / 2 - t, -iy / 2 - t, 0), (ix / 2 + t, -iy / 2, h)),
        box_mesh((-ix / 2 - t, iy / 2, 0), (ix / 2 + t, iy / 2 + t, h)),
        box_mesh((-ix / 2 - t, -iy / 2, 0), (-ix / 2, iy / 2, h)),
        box_mesh((ix / 2, -iy / 2, 0), (ix / 2 + t, iy / 2, h)),
    ]
    box_mesh_all = trimesh.util.concatenate(walls)
    box = ColliderSpec(
        "box",
        np.asarray(box_mesh_all.vertices),
        np.asarray(box_mesh_all.faces),
        planar_pose(*cfg.box_pose),
        ContactSpec(0.0, 0.5),
        mesh_surface_gaussians(box_mesh_all, BOX_RGB, spacing=0.003),
    )
    sim = SimParams(
        dt=1.0 / 30.0 / cfg.substeps,
        substeps=cfg.substeps,
        ground_restitution=0.0,
        ground_friction=cfg.ground_friction,
        object_collision=False,
        self_collision=True,
        collision_dist=0.6 * cfg.spacing,
        candidate_radius_scale=2.0,
        mesh_margin=0.002,
    )
    return TwinSpec(
        name=f"toy-packing-{preset}",
        robot=gripper_robot(cfg.finger_friction, cfg.robot_gaussian_spacing, cfg.ee_frame),
        objects=(toy,),
        colliders=(box,),
        cameras=study_cameras(TOY_CROP, TOY_CROP, cfg.image_hw)
        if cfg.study_cameras
        else (front_camera(cfg.image_hw), wrist_camera("link7", cfg.image_hw)),
        background=workcell_background(),
        sim=sim,
    )
