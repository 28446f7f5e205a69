"""Built-in procedural cells (no download), produced as TwinSpecs like any twin loaded from disk.

The reference workcell: a procedural table and backdrop (Gaussians), the built-in xArm-7-like arm with
the reference cameras (a fixed front camera and a wrist camera, DESIGN §5), and the task's objects.

- `push_t_cell(preset)`: the arm with a vertical pusher held at a fixed height above the table, and a
  T-block made of particles (volume lattice, springs within a radius, max 50 neighbours, uniform
  Y = 3e4) whose coloured surface Gaussians follow its rigid motion. Presets: `reference` (5 mm
  lattice, 667 substeps per 30 Hz frame, PhysTwin's dt = 5e-5 s) and `fast` (15 mm lattice, 100
  substeps, about 50x cheaper; the demo and the tests use it).
"""

from __future__ import annotations

from dataclasses import dataclass, fields, replace

from twinbench.gaussians.camera import look_at_pose
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.physics import SimParams
from twinbench.robot.controller import ControllerConfig
from twinbench.transforms import planar_pose
from twinbench.twin.assets import backdrop_gaussians, mesh_surface_gaussians, table_gaussians
from twinbench.twin.spec import CameraSpec, ContactSpec, ObjectSpec, RobotSpec, TwinSpec

# (fx, fy, cx, cy) of the reference cell's cameras (DESIGN §5); both sensors are 848x480.
FRONT_INTRINSICS = (427.29, 426.79, 430.00, 242.81)
WRIST_INTRINSICS = (433.26, 433.26, 425.70, 244.70)


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

    @staticmethod
    def preset(name: str, **overrides) -> PushTCell:
        presets = {"reference": PushTCell(), "fast": PushTCell(particle_spacing=0.015, substeps=100)}
        if name not in presets:
            raise ValueError(f"push-t preset must be one of {sorted(presets)}, got {name!r}")
        known = {f.name for f in fields(PushTCell)}
        unknown = sorted(set(overrides) - known)
        if unknown:
            raise ValueError(f"push-t cell: unknown setting(s) {unknown}; known: {sorted(known)}")
        return replace(presets[name], **overrides)


def push_t_cell(preset: str = "reference", **overrides) -> TwinSpec:
    """The built-in push-T twin (see the module docstring)."""
    from twinbench.tasks.push_t_geometry import TBlockShape, sample_block_particles

    cfg = PushTCell.preset(preset, **overrides)
    shape = TBlockShape()
    block = ObjectSpec(
        "tblock",
        sample_block_particles(shape, cfg.particle_spacing),
        spring_Y=3e4,
        spring_radius=cfg.spring_radius_factor * cfg.particle_spacing,
        max_neighbors=50,
        gaussians=mesh_surface_gaussians(shape.mesh(), (0.30, 0.42, 0.68)),
        binding="rigid",
        rest_pose=planar_pose(*cfg.block_pose),
    )
    sim = SimParams(
        dt=1.0 / cfg.fps / cfg.substeps,
        substeps=cfg.substeps,
        ground_restitution=0.0,
        ground_friction=cfg.ground_friction,
        object_collision=False,
        mesh_margin=0.6 * cfg.particle_spacing,
    )
    robot = RobotSpec(
        "builtin:xarm7_pusher",
        scan_spacing=cfg.robot_gaussian_spacing,
        tool_contact=ContactSpec(0.0, cfg.pusher_friction),
    )
    return TwinSpec(
        name=f"push-t-{preset}",
        robot=robot,
        objects=(block,),
        cameras=(front_camera(cfg.image_hw), wrist_camera("link7", cfg.image_hw)),
        background=workcell_background(),
        sim=sim,
        controller=ControllerConfig(action_mode="planar", planar_height=cfg.pusher_height),
    )
