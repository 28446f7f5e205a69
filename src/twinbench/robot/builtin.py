"""The built-in arm (no download): xArm 7 kinematics, procedural link meshes, gripper or pusher tool.

Regenerate the committed assets with `python -m twinbench.robot.builtin --regenerate`.

Kinematics copied from the official xArm 7 URDF (`xarm_description`, as shipped in the PyPI package
example-robot-data 6.0.0, `robots/xarm_description/urdf/xarm7.urdf`); every joint axis is local z and
the `rpy` angles of +-1.5708 there are written here as exact +-pi/2:

    joint   parent -> child         origin xyz (m)           origin rpy     limits (rad)
    joint1  link_base -> link1      (0, 0, 0.267)            (0, 0, 0)      [-2pi, 2pi]
    joint2  link1 -> link2          (0, 0, 0)                (-pi/2, 0, 0)  [-2.059, 2.0944]
    joint3  link2 -> link3          (0, -0.293, 0)           (pi/2, 0, 0)   [-2pi, 2pi]
    joint4  link3 -> link4          (0.0525, 0, 0)           (pi/2, 0, 0)   [-0.19198, 3.927]
    joint5  link4 -> link5          (0.0775, -0.3425, 0)     (pi/2, 0, 0)   [-2pi, 2pi]
    joint6  link5 -> link6          (0, 0, 0)                (pi/2, 0, 0)   [-1.69297, pi]
    joint7  link6 -> link7          (0.076, 0.097, 0)        (-pi/2, 0, 0)  [-2pi, 2pi]

(velocity limit 3.14 rad/s; effort 50, 50, 30, 30, 30, 20, 20 N m). At q = 0 the flange (link7 origin)
is at (0.206, 0, 0.1205) m pointing down. Tools, fixed to the flange (link7 z = approach direction):

- gripper: palm 15-85 mm below the flange, two prismatic fingers (`left_finger_joint` drives, the right
  one mimics it with multiplier 1 along the opposite axis); each finger moves 0 to 42.5 mm, so the
  opening is 0 to 85 mm; end-effector `tcp` at 130 mm (15 mm above the fingertips at 145 mm).
- pusher: a vertical rod of radius 15 mm from the flange to 150 mm; `tcp` at the rod tip.
- pusher20: the reference study's 20 cm pusher (kywind/real2sim-eval `xarm7_with_pusher.urdf`, its mesh
  `pusher_20cm.stl` measured): a 37.5 mm radius plate up to 18.5 mm below the flange and a rod of radius
  10.2 mm whose tip is 215 mm below the flange (the mesh's 200 mm mounted 15 mm down); `tcp` at the tip.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import trimesh

from twinbench.robot.model import RobotModel, load_robot

ASSETS = Path(__file__).resolve().parent / "assets"
TOOLS = ("gripper", "pusher", "pusher20")
HALF_PI = np.pi / 2

# (name, parent, child, xyz, rpy, lower, upper, effort)
XARM7_JOINTS = [
    ("joint1", "link_base", "link1", (0.0, 0.0, 0.267), (0.0, 0.0, 0.0), -2 * np.pi, 2 * np.pi, 50.0),
    ("joint2", "link1", "link2", (0.0, 0.0, 0.0), (-HALF_PI, 0.0, 0.0), -2.059, 2.0944, 50.0),
    ("joint3", "link2", "link3", (0.0, -0.293, 0.0), (HALF_PI, 0.0, 0.0), -2 * np.pi, 2 * np.pi, 30.0),
    ("joint4", "link3", "link4", (0.0525, 0.0, 0.0), (HALF_PI, 0.0, 0.0), -0.19198, 3.927, 30.0),
    ("joint5", "link4", "link5", (0.0775, -0.3425, 0.0), (HALF_PI, 0.0, 0.0), -2 * np.pi, 2 * np.pi, 30.0),
    ("joint6", "link5", "link6", (0.0, 0.0, 0.0), (HALF_PI, 0.0, 0.0), -1.69297, np.pi, 20.0),
    ("joint7", "link6", "link7", (0.076, 0.097, 0.0), (-HALF_PI, 0.0, 0.0), -2 * np.pi, 2 * np.pi, 20.0),
]
LINK_RADIUS = {
    "link1": 0.055,
    "link2": 0.052,
    "link3": 0.048,
    "link4": 0.048,
    "link5": 0.045,
    "link6": 0.042,
    "link7": 0.04,
}
LINK_COLORS = {
    "link_base": (0.25, 0.25, 0.27),
    "link1": (0.92, 0.92, 0.90),
    "link2": (0.85, 0.86, 0.88),
    "link3": (0.92, 0.92, 0.90),
    "link4": (0.85, 0.86, 0.88),
    "link5": (0.92, 0.92, 0.90),
    "link6": (0.85, 0.86, 0.88),
    "link7": (0.30, 0.30, 0.32),
    "gripper_base": (0.18, 0.18, 0.20),
    "left_finger": (0.55, 0.20, 0.15),
    "right_finger": (0.15, 0.25, 0.55),
    "pusher": (0.85, 0.45, 0.10),
}

FINGER_TRAVEL = 0.0425  # m per finger (opening 0..85 mm)
PALM_Z = (0.015, 0.085)  # palm extent below the flange (m)
FINGER_SIZE = (0.02, 0.01, 0.06)  # x, y (thickness), z (length) in m
GRIPPER_TCP_Z = 0.13
PUSHER_RADIUS = 0.015
PUSHER_LENGTH = 0.15
# Each pusher tool: (rod radius, tip below the flange, mount plate radius, plate bottom below the flange), m.
PUSHERS = {"pusher": (PUSHER_RADIUS, PUSHER_LENGTH, 0.04, 0.015), "pusher20": (0.0102, 0.215, 0.0375, 0.0185)}
# Home pose of the end-effector (both tools): 35 cm in front of the base, 25 cm above the table, pointing
# down (tcp z = -world z, tcp x = world x), i.e. wxyz (0, 1, 0, 0).
HOME_POSITION = (0.35, 0.0, 0.25)
HOME_QUAT = (0.0, 1.0, 0.0, 0.0)


def _rod(p0, p1, radius: float) -> trimesh.Trimesh:
    return trimesh.creation.cylinder(radius=radius, segment=np.array([p0, p1], dtype=np.float64), sections=20)


def _l_path(offset, radius: float) -> list[trimesh.Trimesh]:
    """Rods from the origin to `offset` along x, then y, then z (skipping short legs)."""
    parts, cur = [], np.zeros(3)
    for axis in range(3):
        nxt = cur.copy()
        nxt[axis] = offset[axis]
        if abs(offset[axis]) > 0.01:
            parts.append(_rod(cur, nxt, radius))
        cur = nxt
    return parts


def _arm_meshes() -> dict[str, trimesh.Trimesh]:
    meshes = {
        "link_base": trimesh.util.concatenate(
            [_rod((0, 0, 0), (0, 0, 0.02), 0.08), _rod((0, 0, 0.02), (0, 0, 0.267 - 0.055), 0.06)]
        )
    }
    child_offset = {parent: np.array(xyz) for _, parent, _, xyz, *_ in XARM7_JOINTS}
    for link, r in LINK_RADIUS.items():
        if link == "link7":
            parts = [_rod((0, 0, -0.05), (0, 0, 0.0), r)]
        else:
            parts = [_rod((0, 0, -r), (0, 0, r), r)] + _l_path(child_offset[link], 0.8 * r)
        meshes[link] = trimesh.util.concatenate(parts)
    return meshes


def _tool_meshes(tool: str) -> dict[str, trimesh.Trimesh]:
    if tool == "gripper":
        palm = trimesh.util.concatenate(
            [
                _rod((0, 0, 0), (0, 0, PALM_Z[0]), 0.04),
                trimesh.creation.box(
                    extents=(0.05, 0.13, PALM_Z[1] - PALM_Z[0]),
                    transform=trimesh.transformations.translation_matrix(
                        (0, 0, 0.5 * (PALM_Z[0] + PALM_Z[1]))
                    ),
                ),
            ]
        )
        fx, fy, fz = FINGER_SIZE
        left = trimesh.creation.box(
            extents=(fx, fy, fz), transform=trimesh.transformations.translation_matrix((0, fy / 2, fz / 2))
        )
        right = trimesh.creation.box(
            extents=(fx, fy, fz), transform=trimesh.transformations.translation_matrix((0, -fy / 2, fz / 2))
        )
        return {"gripper_base": palm, "left_finger": left, "right_finger": right}
    if tool in PUSHERS:
        radius, length, plate_radius, plate = PUSHERS[tool]
        mount = _rod((0, 0, 0), (0, 0, plate), plate_radius)
        rod = _rod((0, 0, plate), (0, 0, length), radius)
        return {"pusher_mount": mount, "pusher": rod}
    raise ValueError(f"tool: expected one of {TOOLS}, got {tool!r}")


def _fmt(v) -> str:
    return " ".join(repr(float(x)) for x in v)


def _link_xml(name: str, mesh_file: str | None, color) -> str:
    if mesh_file is None:
        return f'  <link name="{name}"/>\n'
    geom = f'<geometry><mesh filename="{mesh_file}"/></geometry>'
    rgba = _fmt((*color, 1.0))
    return (
        f'  <link name="{name}">\n'
        f'    <visual><origin xyz="0 0 0" rpy="0 0 0"/>{geom}'
        f'<material name="{name}_color"><color rgba="{rgba}"/></material></visual>\n'
        f'    <collision><origin xyz="0 0 0" rpy="0 0 0"/>{geom}</collision>\n'
        f"  </link>\n"
    )


def _joint_xml(name, jtype, parent, child, xyz, rpy, axis=(0, 0, 1), limits=None, mimic=None) -> str:
    s = (
        f'  <joint name="{name}" type="{jtype}">\n    <parent link="{parent}"/>\n'
        f'    <child link="{child}"/>\n'
        f'    <origin xyz="{_fmt(xyz)}" rpy="{_fmt(rpy)}"/>\n'
    )
    if jtype != "fixed":
        s += f'    <axis xyz="{_fmt(axis)}"/>\n'
    if limits is not None:
        lo, hi, effort, vel = limits
        s += f'    <limit lower="{lo!r}" upper="{hi!r}" effort="{effort!r}" velocity="{vel!r}"/>\n'
    if mimic is not None:
        s += f'    <mimic joint="{mimic}" multiplier="1.0" offset="0.0"/>\n'
    return s + "  </joint>\n"


def write_urdf(tool: str, folder: Path = ASSETS) -> Path:
    """Write meshes (STL) and the URDF of the built-in arm with `tool`; returns the URDF path."""
    tool_meshes = _tool_meshes(tool)
    prefix = "pusher20_" if tool == "pusher20" else ""  # its tool's meshes beside the 15 mm pusher's
    meshes = {**_arm_meshes(), **tool_meshes}
    files = {name: f"{prefix if name in tool_meshes else ''}{name}.stl" for name in meshes}
    mesh_dir = folder / "meshes"
    mesh_dir.mkdir(parents=True, exist_ok=True)
    for name, mesh in meshes.items():
        mesh.export(mesh_dir / files[name])
    links = [_link_xml(n, f"meshes/{files[n]}", LINK_COLORS.get(n, LINK_COLORS["link7"])) for n in meshes]
    joints = [
        _joint_xml(n, "revolute", p, c, xyz, rpy, limits=(lo, hi, eff, 3.14))
        for n, p, c, xyz, rpy, lo, hi, eff in XARM7_JOINTS
    ]
    if tool == "gripper":
        links.append(_link_xml("tcp", None, None))
        joints += [
            _joint_xml("gripper_fix", "fixed", "link7", "gripper_base", (0, 0, 0), (0, 0, 0)),
            _joint_xml(
                "left_finger_joint",
                "prismatic",
                "gripper_base",
                "left_finger",
                (0, 0, PALM_Z[1]),
                (0, 0, 0),
                axis=(0, 1, 0),
                limits=(0.0, FINGER_TRAVEL, 50.0, 0.2),
            ),
            _joint_xml(
                "right_finger_joint",
                "prismatic",
                "gripper_base",
                "right_finger",
                (0, 0, PALM_Z[1]),
                (0, 0, 0),
                axis=(0, -1, 0),
                limits=(0.0, FINGER_TRAVEL, 50.0, 0.2),
                mimic="left_finger_joint",
            ),
            _joint_xml("tcp_fix", "fixed", "gripper_base", "tcp", (0, 0, GRIPPER_TCP_Z), (0, 0, 0)),
        ]
    else:
        links.append(_link_xml("tcp", None, None))
        joints += [
            _joint_xml("pusher_mount_fix", "fixed", "link7", "pusher_mount", (0, 0, 0), (0, 0, 0)),
            _joint_xml("pusher_fix", "fixed", "link7", "pusher", (0, 0, 0), (0, 0, 0)),
            _joint_xml("tcp_fix", "fixed", "link7", "tcp", (0, 0, PUSHERS[tool][1]), (0, 0, 0)),
        ]
    text = (
        '<?xml version="1.0"?>\n<!-- Generated by twinbench.robot.builtin (run it with the regenerate flag); '
        "xArm 7 kinematics (see builtin.py). Do not edit by hand. -->\n"
        f'<robot name="twinbench_xarm7_{tool}">\n' + "".join(links) + "".join(joints) + "</robot>\n"
    )
    path = folder / f"xarm7_{tool}.urdf"
    path.write_text(text)
    return path


def _tool_meta(tool: str) -> dict:
    if tool == "gripper":
        return {
            "ee_link": "tcp",
            "gripper_joint": "left_finger_joint",
            "gripper_open": FINGER_TRAVEL,
            "gripper_closed": 0.0,
            "contact_links": ["left_finger", "right_finger"],
        }
    return {"ee_link": "tcp", "gripper_joint": None, "contact_links": ["pusher"]}


def regenerate(folder: Path = ASSETS) -> list[Path]:
    """Write both tools' URDFs and meshes plus a JSON sidecar with the end-effector, gripper and home q."""
    from twinbench.robot.ik import solve_ik
    from twinbench.transforms import pose_matrix

    written = []
    for tool in TOOLS:
        urdf = write_urdf(tool, folder)
        meta = _tool_meta(tool)
        model = load_robot(urdf, **meta)
        q0 = model.set_gripper(np.zeros(model.n_q), 0.0)
        res = solve_ik(model, pose_matrix(np.array(HOME_POSITION), np.array(HOME_QUAT)), q0, restarts=0)
        if not res.converged:
            raise RuntimeError(f"home pose IK did not converge for tool {tool!r}")
        meta["home_q"] = [round(float(v), 10) for v in res.q]
        side = urdf.with_suffix(".json")
        side.write_text(json.dumps(meta, indent=2) + "\n")
        written += [urdf, side]
    return written


def load_builtin_arm(tool: str = "gripper", *, load_meshes: bool = True) -> RobotModel:
    """The built-in xArm-7-like arm with a parallel gripper (`tool="gripper"`) or a pusher (`"pusher"`,
    `"pusher20"`)."""
    if tool not in TOOLS:
        raise ValueError(f"tool: expected one of {TOOLS}, got {tool!r}")
    urdf = ASSETS / f"xarm7_{tool}.urdf"
    side = urdf.with_suffix(".json")
    if not urdf.is_file() or not side.is_file():
        raise FileNotFoundError(
            f"built-in robot assets missing ({urdf}); run `python -m twinbench.robot.builtin --regenerate`"
        )
    meta = json.loads(side.read_text())
    meta["home_q"] = np.asarray(meta["home_q"], dtype=np.float64)
    return load_robot(urdf, load_meshes=load_meshes, **meta)


def xarm7_urdf_path() -> Path:
    """Path of the real xArm 7 URDF from the `example-robot-data` package (extra `xarm`)."""
    import importlib.metadata as md

    try:
        dist = md.distribution("example-robot-data")
    except md.PackageNotFoundError as exc:
        raise ModuleNotFoundError(
            "the real xArm 7 model needs the optional extra `xarm` (pip install 'twinbench[xarm]', "
            "i.e. example-robot-data==6.0.0)"
        ) from exc
    path = Path(
        str(dist.locate_file("cmeel.prefix/share/example-robot-data/robots/xarm_description/urdf/xarm7.urdf"))
    )
    if not path.is_file():
        raise FileNotFoundError(f"example-robot-data is installed but has no xArm 7 URDF at {path}")
    return path


def load_xarm7(*, load_meshes: bool = True) -> RobotModel:
    """The real xArm 7 (no tool; end-effector = flange `link_eef`) from example-robot-data."""
    home = json.loads((ASSETS / "xarm7_pusher.json").read_text())["home_q"]
    return load_robot(
        xarm7_urdf_path(), ee_link="link_eef", home_q=np.asarray(home[:7]), load_meshes=load_meshes
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--regenerate", action="store_true", help="rewrite the URDFs + meshes under assets/")
    args = parser.parse_args(argv)
    if not args.regenerate:
        parser.print_help()
        return 0
    for path in regenerate():
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
