"""`twinbench twin build`: a twin directory from a build config that names the construction steps'
outputs (aligned robot, colour maps, objects, colliders, calibration); see `build_spec_from_config`."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from twinbench.construct.align_robot import read_aligned_robot
from twinbench.construct.calibration import load_calibration
from twinbench.construct.mesh_object import load_mesh
from twinbench.errors import check_name
from twinbench.gaussians.io import load_gaussians

_BUILD_FIELDS = {"name", "robot", "background", "objects", "colliders", "cameras", "sim", "controller",
                 "render"}
_ROBOT_PASS = {"ee_link", "contact_links", "gripper_joint", "gripper_open", "gripper_closed", "home_q",
               "scan_spacing", "tool_radius", "contact_mesh"}


def _color_map_file(root: Path, value, where: str):
    from twinbench.twin import ColorMap

    if value is None:
        return None
    doc = json.loads((root / value).read_text())
    try:
        return ColorMap(int(doc["degree"]), np.asarray(doc["coeffs"], dtype=np.float64))
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"{root / value}: {where}: not a colour map {{degree, coeffs}} ({exc})") from exc


def _known(d: dict, allowed: set, where: str, config: Path) -> dict:
    if not isinstance(d, dict):
        raise ValueError(f"{config}: {where} must be an object")
    unknown = set(d) - allowed
    if unknown:
        raise ValueError(f"{config}: {where}: unknown field(s) {sorted(unknown)}; known: {sorted(allowed)}")
    return d


def build_spec_from_config(config_path):
    """The TwinSpec a build config describes (see `_build_spec` for the format); a config whose fields
    have the wrong types or keys is a ValueError naming the file."""
    try:
        return _build_spec(config_path)
    except (KeyError, TypeError, AttributeError, IndexError) as exc:
        raise ValueError(f"{config_path}: not a valid build config ({type(exc).__name__}: {exc}); see "
                         "twinbench.construct.build_config for its fields") from None


def _build_spec(config_path):
    """The TwinSpec described by a build config (JSON; paths relative to its folder):

        {"name": "my-cell",
         "robot": {"aligned": "aligned/" | null, "urdf": "builtin:xarm7_gripper" (default: the aligned
                   folder's), "color_map": "color/color_map.json" | null, "tool_contact": {...},
                   ee_link, contact_links, gripper_joint, gripper_open, gripper_closed, home_q, scan_spacing,
                   tool_radius, contact_mesh ("collision" | "convex_hull")},
         "background": {"gaussians": "aligned/aligned/background.ply" | null, "color_map": null},
         "objects": [{"dir": "objects/tblock", "rest_pose": 4x4 | null,
                      "gaussians": "world-frame .ply replacing the object's own" | null, "color_map": null}],
         "colliders": [{"name", "mesh", "pose", "restitution", "friction",
                        "gaussians": ".ply in the collider's frame" | null, "color_map": null,
                        "channel": [width, depth, length] | null (see ColliderSpec.channel)}],
         "cameras": "calibration.json",
         "sim": {SimParams fields over the first object's}, "controller": {...},
         "render": {"background": rgb}}
    """
    import dataclasses

    from twinbench.physics import SimParams
    from twinbench.robot.controller import ControllerConfig
    from twinbench.transforms import invert_pose
    from twinbench.twin import ColliderSpec, ContactSpec, RobotSpec, TwinSpec, load_object

    config = Path(config_path)
    root = config.parent
    try:
        doc = json.loads(config.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{config}: cannot read the build config ({exc})") from exc
    _known(doc, _BUILD_FIELDS, "top level", config)
    for req in ("robot", "objects", "cameras"):
        if req not in doc:
            raise ValueError(f"{config}: missing field {req!r}")

    r = _known(doc["robot"], _ROBOT_PASS | {"aligned", "urdf", "color_map", "tool_contact"}, "robot", config)
    kw = {k: (tuple(v) if isinstance(v, list) else v) for k, v in r.items() if k in _ROBOT_PASS}
    urdf = r.get("urdf")
    if r.get("aligned") is not None:
        cloud, labels, links, q, aligned_urdf = read_aligned_robot(root / r["aligned"])
        urdf = urdf or aligned_urdf
        kw.update(gaussians=cloud, gaussian_labels=labels, gaussian_links=tuple(links), gaussians_q=tuple(q))
    if not urdf:
        raise ValueError(f"{config}: robot.urdf is needed when robot.aligned is not given")
    if not str(urdf).startswith("builtin:"):
        urdf = str((root / urdf).resolve())
    if r.get("tool_contact") is not None:
        kw["tool_contact"] = ContactSpec(**r["tool_contact"])
    robot = RobotSpec(urdf=urdf, color_map=_color_map_file(root, r.get("color_map"), "robot.color_map"), **kw)

    bg = _known(doc.get("background") or {}, {"gaussians", "color_map"}, "background", config)
    background = load_gaussians(root / bg["gaussians"]) if bg.get("gaussians") else None

    objects, sim = [], {}
    for i, o in enumerate(doc["objects"]):
        o = _known(o, {"dir", "name", "rest_pose", "gaussians", "color_map"}, f"objects[{i}]", config)
        obj, osim = load_object(root / o["dir"])
        if i == 0:
            sim = dict(osim)
        changes = {}
        if o.get("name"):
            changes["name"] = check_name(o["name"], f"{config}: objects[{i}].name")
        if o.get("rest_pose") is not None:
            changes["rest_pose"] = np.asarray(o["rest_pose"], dtype=np.float64)
        rest = changes.get("rest_pose", obj.rest_pose)
        if o.get("gaussians"):
            changes["gaussians"] = load_gaussians(root / o["gaussians"]).transform(invert_pose(rest))
        if o.get("color_map"):
            changes["color_map"] = _color_map_file(root, o["color_map"], f"objects[{i}].color_map")
        objects.append(dataclasses.replace(obj, **changes))

    colliders = []
    for i, c in enumerate(doc.get("colliders") or []):
        fields = {"name", "mesh", "pose", "restitution", "friction", "gaussians", "color_map", "channel"}
        c = _known(c, fields, f"colliders[{i}]", config)
        check_name(c.get("name"), f"{config}: colliders[{i}].name")
        mesh = load_mesh(root / c["mesh"])
        colliders.append(ColliderSpec(
            c["name"], np.asarray(mesh.vertices), np.asarray(mesh.faces),
            np.asarray(c.get("pose", np.eye(4)), dtype=np.float64),
            ContactSpec(c.get("restitution", 0.0), c.get("friction", 0.5)),
            load_gaussians(root / c["gaussians"]) if c.get("gaussians") else None,
            _color_map_file(root, c.get("color_map"), f"colliders[{i}].color_map"),
            None if c.get("channel") is None else tuple(c["channel"]),
        ))
    cams = doc["cameras"]
    if not isinstance(cams, str):
        raise ValueError(f"{config}: cameras must name a calibration file "
                         "(see twinbench.construct.calibration)")
    cameras = load_calibration(root / cams)
    sim.update(doc.get("sim") or {})
    extra = {}
    if doc.get("render", {}).get("background") is not None:
        extra["render_background"] = tuple(doc["render"]["background"])
    known_sim = {f.name for f in dataclasses.fields(SimParams)}
    bad = sorted(set(sim) - known_sim)
    if bad:
        raise ValueError(f"{config}: sim: unknown SimParams field(s) {bad}")
    sim = {k: (tuple(v) if isinstance(v, list) else v) for k, v in sim.items()}
    ctrl = {k: (tuple(v) if isinstance(v, list) else v) for k, v in (doc.get("controller") or {}).items()}
    return TwinSpec(
        name=doc.get("name", config.stem), robot=robot, objects=tuple(objects), cameras=tuple(cameras),
        background=background, background_color_map=_color_map_file(root, bg.get("color_map"), "background"),
        colliders=tuple(colliders), sim=SimParams(**sim), controller=ControllerConfig(**ctrl), **extra,
    )


def build_from_config(config_path, out) -> Path:
    """`twinbench twin build CONFIG --out TWIN_DIR`: write the twin directory a build config describes."""
    from twinbench.errors import InputError
    from twinbench.twin import save_twin
    from twinbench.twin.build import load_spec_robot, warn_heavy_contact_mesh

    spec = build_spec_from_config(config_path)
    try:  # the robot's fields against its URDF (links, joints, home_q) before anything is written
        robot = load_spec_robot(spec.robot)
    except (InputError, KeyError) as err:
        raise ValueError(f"{config_path}: robot: {str(err).strip(chr(34) + chr(39))}") from None
    for link in robot.contact_links:
        warn_heavy_contact_mesh(robot, link)
    return save_twin(spec, out)
