"""`twinbench twin export|show|build`: write a task's built-in twin as a directory; summarise and preview
one; write a twin directory from a build config (twinbench.construct.build_config)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import numpy as np
import tyro


@dataclass(frozen=True)
class ExportConfig:
    """Write the built-in twin of a task as a twin directory (twin.json + .ply + .npz)."""

    path: Annotated[Path | None, tyro.conf.Positional, tyro.conf.arg(metavar="PATH")] = None
    """the twin directory to write (or --out PATH, as the other commands take it)"""
    out: Path | None = None
    """the same as PATH"""
    task: str = "push-t"
    """the task whose built-in cell is written"""
    preset: str = "reference"
    """the cell's preset (push-t: 'reference' or 'fast')"""


@dataclass(frozen=True)
class ShowConfig:
    """Print a twin directory's parts, counts, cameras and physics settings; write a PNG per camera."""

    twin: tyro.conf.Positional[Path]
    """the twin directory"""
    task: str | None = None
    """render at this task's first grid state (default: every object at its rest pose)"""
    out_dir: Path | None = None
    """where the PNGs go (default: outputs/twin_show/<twin name>)"""
    device: str = "cpu"


@dataclass(frozen=True)
class BuildConfig:
    """Write a twin directory from a build config naming the construction steps' outputs."""

    config: tyro.conf.Positional[Path]
    """build config JSON (see twinbench.construct.build_config.build_spec_from_config)"""
    out: Path
    """the twin directory to write"""


TwinCommand = (
    Annotated[ExportConfig, tyro.conf.subcommand("export")]
    | Annotated[ShowConfig, tyro.conf.subcommand("show")]
    | Annotated[BuildConfig, tyro.conf.subcommand("build")]
)


def export(cfg: ExportConfig) -> int:
    from twinbench.tasks import get_task
    from twinbench.twin.files import save_twin

    if (cfg.path is None) == (cfg.out is None):
        raise ValueError("twin export: give the twin directory to write once, as PATH or as --out PATH")
    task = get_task(cfg.task)
    if task.task_cls is None:
        raise ValueError(f"task {cfg.task!r} has no twin (it is a debug task with its own env)")
    spec = task.task_cls().default_twin(cfg.preset)
    path = save_twin(spec, cfg.path or cfg.out)
    print(f"wrote the {cfg.task} twin ({cfg.preset}) to {path.parent}")
    return 0


def _contact_links(robot) -> str:
    """Each contact link with its mesh's faces (and for a convex hull, how far it moved)."""
    parts = []
    for link in robot.contact_links:
        text = f"{link} ({len(robot.contact_faces(link)):,} faces"
        if link in robot.convex_contact_moved:
            text += f", convex hull within {robot.convex_contact_moved[link] * 1000:.1f} mm"
        parts.append(text + ")")
    return "[" + ", ".join(parts) + "]"


def summary(twin) -> list[str]:
    """Human-readable lines describing a built twin."""
    spec, m, robot = twin.spec, twin.model, twin.robot
    p = spec.sim
    lines = [
        f"twin {spec.name!r}",
        f"  robot: {spec.robot.urdf} ({robot.n_q} joints, {robot.n_links} links), "
        f"end-effector {robot.ee_link!r}, "
        f"contact links {_contact_links(robot)}, gripper {robot.gripper_joint or '-'}, "
        f"{len(twin.robot_gaussians)} Gaussians",
        f"  background: {0 if spec.background is None else len(spec.background)} Gaussians",
    ]
    starts = np.cumsum([0] + [o.num_particles for o in spec.objects])
    springs = m.springs_np[: m.num_object_springs]
    for k, o in enumerate(spec.objects):
        n_springs = int(np.sum((springs[:, 0] >= starts[k]) & (springs[:, 0] < starts[k + 1])))
        rule = "explicit" if o.springs is not None else f"radius {o.spring_radius:g} m, max {o.max_neighbors}"
        lines.append(
            f"  object {o.name!r}: {o.num_particles} particles, {n_springs} springs ({rule}), "
            f"{0 if o.gaussians is None else len(o.gaussians)} Gaussians ({o.binding})"
        )
    for c in spec.colliders:
        lines.append(
            f"  collider {c.name!r}: {len(c.faces)} triangles, "
            f"{0 if c.gaussians is None else len(c.gaussians)} Gaussians"
        )
    for c in spec.cameras:
        where = f"on {c.mount_link}" if c.mount_link else "fixed"
        lines.append(
            f"  camera {c.name!r}: {where}, sensor {c.sensor_size[0]}x{c.sensor_size[1]} "
            f"(fx, fy, cx, cy = {', '.join(f'{v:g}' for v in c.intrinsics)}), policy image "
            f"{c.output_hw[1]}x{c.output_hw[0]}{', depth' if c.depth else ''}"
        )
    lines.append(
        f"  physics: dt {p.dt:g} s x {p.substeps} substeps, {m.num_particles} particles, "
        f"{m.num_springs} springs, ground friction {p.ground_friction:g}, collision distance "
        f"{p.collision_dist:g} m, self-collision {p.self_collision}"
    )
    lines.append(f"  controller: {spec.controller.action_mode} actions at {spec.controller.control_hz:g} Hz")
    return lines


def show(cfg: ShowConfig) -> int:
    import imageio.v2 as imageio

    from twinbench.twin import build_twin, load_twin

    spec = load_twin(cfg.twin)
    if cfg.task is None:
        twin, state = build_twin(spec, cfg.device)
    else:
        from twinbench.env import TwinEnv

        env = TwinEnv(cfg.task, twin=spec, device=cfg.device)
        env.reset(seed=0, options={"init_state": 0})
        twin, state = env.twin, env.state
    print("\n".join(summary(twin)))
    out_dir = cfg.out_dir or Path("outputs") / "twin_show" / spec.name
    out_dir.mkdir(parents=True, exist_ok=True)
    for name, out in twin.render(state).items():
        path = out_dir / f"{name}.png"
        imageio.imwrite(path, out.rgb_uint8())
        print(f"  wrote {path}")
    return 0


def build(cfg: BuildConfig) -> int:
    from twinbench.construct.build_config import build_from_config

    path = build_from_config(cfg.config, cfg.out)
    print(f"wrote the twin to {path.parent}")
    return 0


def main(cfg) -> int:
    if isinstance(cfg, BuildConfig):
        return build(cfg)
    return export(cfg) if isinstance(cfg, ExportConfig) else show(cfg)
