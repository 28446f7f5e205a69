"""`twinbench robot-info [URDF]`: links, joints and the home end-effector pose of a robot."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import tyro

from twinbench.robot.builtin import TOOLS, load_builtin_arm
from twinbench.robot.ik import FULL_ORIENTATION_JOINTS
from twinbench.robot.model import HEAVY_CONTACT_FACES, RobotModel, load_robot
from twinbench.transforms import matrix_to_quat


@dataclass(frozen=True)
class RobotInfoConfig:
    """Describe a robot: the built-in arm (no URDF given) or a URDF file."""

    urdf: Annotated[str | None, tyro.conf.Positional] = None  # URDF file; omit for the built-in arm
    tool: str = "gripper"  # built-in arm tool: gripper | pusher (ignored with a URDF)
    ee_link: str | None = None  # end-effector link of a URDF (default: the deepest link not on a finger)
    gripper_joint: str | None = None  # the joint driving a URDF's fingers (twin.json's robot.gripper_joint)
    package_dirs: tuple[str, ...] = ()  # extra folders searched for package:// meshes


def describe(model: RobotModel) -> str:
    """Human-readable summary: links, joints (type, axis, limits, mimic) and the home EE pose."""
    lines = [f"robot {model.name}  ({model.urdf_path})", f"links ({model.n_links}):"]
    for name in model.link_names:
        mesh, col = model.visual_meshes.get(name), model.collision_meshes.get(name)
        extra = f"  mesh: {len(mesh.vertices)} vertices" if mesh is not None else ""
        if col is not None:  # a contact link's collision mesh is refitted every physics substep
            extra += f"  collision: {len(col.faces):,} faces"
        lines.append(f"  {name}{extra}")
    heavy = [n for n, m in model.collision_meshes.items() if len(m.faces) > HEAVY_CONTACT_FACES]
    if heavy:
        lines.append(f"  (collision meshes over {HEAVY_CONTACT_FACES:,} faces: {', '.join(heavy)}; as "
                     'contact links they slow every physics step: robot.contact_mesh "convex_hull" collides '
                     "through their simplified hulls)")
    lines.append(f"joints ({len(model.joints)}, {model.n_q} actuated):")
    for j in model.joints:
        s = f"  {j.name:<22} {j.type:<10} {j.parent} -> {j.child}"
        if j.type != "fixed":
            s += f"  axis [{' '.join(f'{a:+.3f}' for a in j.axis)}]  limits [{j.lower:+.4f}, {j.upper:+.4f}]"
        if j.mimic is not None:
            s += f"  mimic {j.mimic[0]} x{j.mimic[1]:g} {j.mimic[2]:+g}"
        lines.append(s)
    arm = f"arm joints (root to end effector): {', '.join(model.arm_joints)}"
    if model.arm_q_indices.size < FULL_ORIENTATION_JOINTS:
        arm += (f" (fewer than {FULL_ORIENTATION_JOINTS}: a tool pointing down turns about the vertical as "
                "the arm gives it; the planar controller and the tasks' start poses leave that turn free)")
    lines.append(arm)
    home = model.home_q
    ee = model.ee_pose(home)
    quat = matrix_to_quat(ee[:3, :3])
    lines.append(f"home q: [{', '.join(f'{v:.4f}' for v in home)}]")
    lines.append(
        f"end effector {model.ee_link} at home: position [{', '.join(f'{v:.4f}' for v in ee[:3, 3])}] m, "
        f"quaternion wxyz [{', '.join(f'{v:.4f}' for v in quat)}]"
    )
    if model.gripper_joint is not None:
        lines.append(
            f"gripper joint {model.gripper_joint}: open {model.gripper_open:g}, "
            f"closed {model.gripper_closed:g}"
        )
    if model.contact_links:
        lines.append(f"contact links: {', '.join(model.contact_links)}")
    return "\n".join(lines)


def main(config: RobotInfoConfig) -> int:
    if config.urdf is None:
        if config.tool not in TOOLS:
            raise ValueError(f"--tool: expected one of {TOOLS}, got {config.tool!r}")
        model = load_builtin_arm(config.tool)
    else:
        model = load_robot(config.urdf, ee_link=config.ee_link, gripper_joint=config.gripper_joint,
                           package_dirs=config.package_dirs)
    print(describe(model))
    return 0
