"""Twin directories on disk: `load_twin(dir)` / `save_twin(spec, dir)`, and standalone object directories
(`load_object` / `save_object`) that construction tools and system identification write.

A twin directory holds `twin.json` (format "twinbench-twin", `version` 2) and the files it names by
relative paths inside the directory: `.ply` Gaussians, `.npz` arrays (read with allow_pickle=False),
`.obj` / `.stl` / `.ply` meshes, and the robot's URDF (or a built-in robot name). The layout of every
field is in README.md ("Twin directories"). Every problem raises `TwinFormatError` naming the file and
the field; a save followed by a load gives back the same spec, array for array.

Versions: 2 added the geometry that task rules read (an object's `outline`, the robot's `tool_radius`, a
collider's `channel`) and an object's optional `goal_pose`; version 1 files (without them) still load. The
robot's optional `contact_mesh` is written only when it is not the default.
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import zipfile
from pathlib import Path

import numpy as np

from twinbench.errors import InputError
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.io import load_gaussians, save_gaussians
from twinbench.gaussians.response import CameraResponse
from twinbench.physics import SimParams
from twinbench.robot.controller import ControllerConfig
from twinbench.twin.shapes import Outline
from twinbench.twin.spec import (
    CameraSpec,
    ColliderSpec,
    ColorMap,
    ContactSpec,
    ObjectSpec,
    RobotSpec,
    TwinSpec,
)

TWIN_FORMAT, OBJECT_FORMAT, VERSION = "twinbench-twin", "twinbench-object", 2
READABLE_VERSIONS = (1, 2)


MAX_NPZ_BYTES = 1 << 30  # the arrays of one .npz together, as their headers declare them
MAX_JSON_BYTES = 64 << 20
MAX_COORDINATE = 1e3  # m: particles farther from the origin are a unit or file error
# The range of every number of `sim` (SimParams) and `controller` (ControllerConfig), checked at load:
# field -> (lowest, highest, integer). Contact coefficients as the kernels clamp them (DESIGN section 4).
FIELD_RANGES = {
    "sim": {
        "dt": (1e-7, 0.1, False), "substeps": (1, 100_000, True), "gravity": (-1e3, 1e3, False),
        "dashpot_damping": (0.0, 1e6, False), "drag_damping": (0.0, 1e6, False),
        "ground_restitution": (0.0, 1.0, False), "ground_friction": (0.0, 2.0, False),
        "object_restitution": (0.0, 1.0, False), "object_friction": (0.0, 2.0, False),
        "collision_dist": (1e-6, 1.0, False), "max_collision_candidates": (1, 10_000, True),
        "candidate_radius_scale": (1.0, 100.0, False), "mesh_margin": (0.0, 1.0, False),
        "spring_Y_min": (0.0, 1e15, False), "spring_Y_max": (0.0, 1e15, False),
    },
    "controller": {
        "max_joint_delta": (1e-6, 10.0, False), "velocity_gain": (1e-6, 100.0, False),
        "velocity_dt": (1e-6, 10.0, False), "control_hz": (0.1, 1000.0, False),
        "gripper_rate": (1e-6, 1.0, False), "grasp_force_threshold": (0.0, 1e12, False),
        "planar_height": (-10.0, 10.0, False), "planar_quat": (-1.0, 1.0, False),
        "ik_max_iters": (1, 10_000, True), "ik_restarts": (0, 100, True),
    },
}


class TwinFormatError(InputError):
    """A twin or object directory that cannot be loaded; the message names the file, the field and the fix."""


class _Reader:
    """Validating reader of one JSON document whose paths are relative to `root`."""

    def __init__(self, root: Path, doc_name: str):
        self.root = root.resolve()
        self.doc = doc_name

    def fail(self, field: str, problem: str):
        raise TwinFormatError(f"{self.root / self.doc}: {field}: {problem}")

    def section(self, value, field: str, required: set[str], optional: set[str]) -> dict:
        if not isinstance(value, dict):
            self.fail(field, f"expected a JSON object, got {type(value).__name__}")
        unknown = sorted(set(value) - required - optional)
        if unknown:
            self.fail(field, f"unknown field(s) {unknown}; known: {sorted(required | optional)}")
        missing = sorted(required - set(value))
        if missing:
            self.fail(field, f"missing field(s) {missing}")
        return value

    def name(self, d: dict, field: str) -> tuple[str, str]:
        """An entry's non-empty `name`, and the field label that names it in later errors."""
        name = d["name"]
        if not isinstance(name, str) or not name:
            self.fail(f"{field}.name", f"expected a non-empty string, got {name!r}")
        return name, f"{field}({name})"

    def number(self, value, field: str, *, integer: bool = False) -> float:
        ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
        if not ok or (integer and int(value) != value):
            self.fail(field, f"expected a finite {'integer' if integer else 'number'}, got {value!r}")
        return int(value) if integer else float(value)

    def array(self, value, field: str, shape: tuple) -> np.ndarray:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            self.fail(field, f"expected a numeric array of shape {shape}")
        if arr.shape != shape or not np.all(np.isfinite(arr)):
            self.fail(field, f"expected a finite array of shape {shape}, got shape {arr.shape}")
        return arr

    def path(self, value, field: str) -> Path:
        if not isinstance(value, str) or not value:
            self.fail(field, f"expected a relative file path (string), got {value!r}")
        if Path(value).is_absolute():
            self.fail(field, f"path {value!r} is absolute; paths are relative to the twin directory")
        full = (self.root / value).resolve()
        if not full.is_relative_to(self.root):
            self.fail(field, f"path {value!r} leaves the directory {self.root}; keep every file inside it")
        if not full.is_file():
            self.fail(field, f"file {value!r} does not exist in {self.root}")
        return full

    def npz(self, value, field: str, required: tuple[str, ...], optional: tuple[str, ...] = ()) -> dict:
        path = self.path(value, field)
        try:
            arrays = read_npz(path)
        except ValueError as err:
            self.fail(field, f"{value} {err}")
        except Exception as err:  # noqa: BLE001 - a damaged archive (BadZipFile, zlib.error, EOFError, ...)
            self.fail(field, f"{value} is not a readable .npz ({type(err).__name__}: {err})")
        unknown = sorted(set(arrays) - set(required) - set(optional))
        missing = sorted(set(required) - set(arrays))
        if missing or unknown:
            self.fail(
                field,
                f"{value}: missing array(s) {missing}, unknown array(s) {unknown}; "
                f"expected {list(required)} and optionally {list(optional)}",
            )
        return arrays

    def gaussians(self, value, field: str) -> GaussianCloud | None:
        if value is None:
            return None
        path = self.path(value, field)
        try:
            return load_gaussians(path)
        except ValueError as err:
            self.fail(field, str(err))

    def mesh(self, value, field: str) -> tuple[np.ndarray, np.ndarray]:
        import trimesh

        path = self.path(value, field)
        try:
            mesh = trimesh.load(path, force="mesh", process=False)
        except Exception as err:  # noqa: BLE001 - trimesh raises many types for a bad file
            self.fail(field, f"{value} is not a readable mesh ({type(err).__name__}: {err})")
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            self.fail(field, f"{value} holds no triangles")
        return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)

    def color_map(self, value, field: str) -> ColorMap | None:
        if value is None:
            return None
        d = self.section(value, field, {"degree", "coeffs"}, set())
        degree = self.number(d["degree"], f"{field}.degree", integer=True)
        try:
            return ColorMap(degree, np.asarray(d["coeffs"], dtype=np.float64))
        except (TypeError, ValueError) as err:
            self.fail(f"{field}.coeffs", str(err))

    def dataclass(self, cls, value, field: str):
        """A frozen config dataclass (SimParams, ControllerConfig) from a JSON object of its fields, each
        number in its range (`FIELD_RANGES[field]`)."""
        names = {f.name for f in dataclasses.fields(cls)}
        d = self.section(value, field, set(), names)
        kwargs = {}
        for f in dataclasses.fields(cls):
            if f.name in d:
                v = d[f.name]
                if f.name in FIELD_RANGES.get(field, {}):
                    self.in_range(v, f"{field}.{f.name}", *FIELD_RANGES[field][f.name])
                elif isinstance(f.default, bool) and not isinstance(v, bool):
                    self.fail(f"{field}.{f.name}", f"expected true or false, got {v!r}")
                kwargs[f.name] = tuple(v) if isinstance(v, list) else v
        try:
            return cls(**kwargs)
        except (TypeError, ValueError) as err:
            self.fail(field, str(err))

    def in_range(self, value, field: str, lo: float, hi: float, integer: bool) -> None:
        """A number (or a list of numbers) within [lo, hi], integers where `integer`."""
        for v in value if isinstance(value, list) else [value]:
            ok = isinstance(v, int if integer else int | float) and not isinstance(v, bool)
            if not ok or not lo <= v <= hi:  # NaN and infinities fail too
                self.fail(field, f"expected {'an integer' if integer else 'a number'} in [{lo:g}, {hi:g}], "
                                 f"got {v!r}")

    def build(self, make, field: str):
        """Call a spec constructor, turning its ValueError into a TwinFormatError naming the field."""
        try:
            return make()
        except TwinFormatError:
            raise
        except (TypeError, ValueError) as err:
            self.fail(field, str(err))


def _read_json(path: Path, kind: str) -> dict:
    if not path.is_file():
        raise TwinFormatError(f"{path}: not found; a {kind} directory holds a {path.name}")
    if path.stat().st_size > MAX_JSON_BYTES:
        raise TwinFormatError(f"{path}: larger than {MAX_JSON_BYTES >> 20} MiB; arrays go in .npz files")
    try:
        doc = json.loads(path.read_text())
    except (json.JSONDecodeError, UnicodeDecodeError) as err:
        raise TwinFormatError(f"{path}: not valid JSON ({err})") from None
    except RecursionError:
        raise TwinFormatError(f"{path}: nested too deeply to be a {kind} file") from None
    return doc


def read_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an .npz, each header read first: plain numeric arrays only (no pickles, no complex
    numbers), all together at most MAX_NPZ_BYTES as declared, and only the declared bytes inflated (a
    member that inflates further is never read whole). ValueError naming the array otherwise."""
    arrays, total = {}, 0
    with zipfile.ZipFile(path) as zf:
        for info in zf.infolist():
            name = info.filename.removesuffix(".npy")
            with zf.open(info) as f:
                try:
                    version = np.lib.format.read_magic(f)
                    read = np.lib.format.read_array_header_1_0 if version == (1, 0) else \
                        np.lib.format.read_array_header_2_0
                    shape, _, dtype = read(f)
                except Exception as err:  # noqa: BLE001 - a damaged header (ValueError, SyntaxError, ...)
                    raise ValueError(f"has no readable .npy header for array {name!r} "
                                     f"({type(err).__name__})") from None
            if dtype.hasobject:
                raise ValueError(f"holds pickled Python objects (array {name!r}), which twinbench never "
                                 "loads; save plain numeric arrays (np.savez)")
            if dtype.kind not in "biuf" or dtype.subdtype is not None or dtype.names:
                raise ValueError(f"has array {name!r} of dtype {dtype}; expected plain numbers (bool, int, "
                                 "float)")
            total += math.prod(shape) * dtype.itemsize
            if total > MAX_NPZ_BYTES:
                raise ValueError(f"declares arrays beyond {MAX_NPZ_BYTES >> 20} MiB (array {name!r} of shape "
                                 f"{shape})")
            with zf.open(info) as f:
                arrays[name] = np.lib.format.read_array(f, allow_pickle=False)
    return arrays


def _check_header(r: _Reader, doc, fmt: str, required: set[str], optional: set[str]) -> dict:
    doc = r.section(doc, "(top level)", {"format", "version"} | required, optional)
    if doc["format"] != fmt:
        r.fail("format", f"expected {fmt!r}, got {doc['format']!r}")
    if doc["version"] not in READABLE_VERSIONS or isinstance(doc["version"], bool):
        r.fail("version", f"this twinbench reads versions {list(READABLE_VERSIONS)}, got {doc['version']!r}")
    return doc


# ---------------------------------------------------------------------------------------------- objects
_OBJECT_FIELDS = (
    {"name", "arrays", "springs", "binding", "rest_pose"},
    {"spring_Y", "mass", "gaussians", "color_map", "outline", "goal_pose"},
)


def _read_outline(r: _Reader, value, field: str) -> Outline | None:
    if value is None:
        return None
    d = r.section(value, field, {"polygon", "height"}, set())
    polygon = d["polygon"]
    if not isinstance(polygon, list) or len(polygon) < 3:
        r.fail(f"{field}.polygon", "expected a list of at least 3 [x, y] vertices (counter-clockwise, "
               "object frame, metres)")
    polygon = r.array(polygon, f"{field}.polygon", (len(polygon), 2))
    height = r.number(d["height"], f"{field}.height")
    return r.build(lambda: Outline(polygon, height), field)


def _read_object(r: _Reader, d, field: str) -> ObjectSpec:
    d = r.section(d, field, *_OBJECT_FIELDS)
    name, field = r.name(d, field)
    springs = d["springs"]
    explicit = springs == "explicit"
    arrays = r.npz(
        d["arrays"], f"{field}.arrays", ("particles",), ("springs", "rest_lengths", "spring_Y", "masses")
    )
    kw: dict = {"particles": arrays["particles"]}
    if not np.all(np.abs(arrays["particles"].astype(np.float64)) <= MAX_COORDINATE):  # NaN fails too
        r.fail(f"{field}.arrays", f"particles must be finite and within {MAX_COORDINATE:g} m of the origin")
    if explicit:
        if "springs" not in arrays:
            r.fail(f"{field}.springs", "'explicit' needs a 'springs' (M, 2) array in the object's npz")
        kw["springs"] = arrays["springs"]
        kw["rest_lengths"] = arrays.get("rest_lengths")
    else:
        rule = r.section(springs, f"{field}.springs", {"radius", "max_neighbors"}, set())
        kw["spring_radius"] = r.number(rule["radius"], f"{field}.springs.radius")
        kw["max_neighbors"] = r.number(rule["max_neighbors"], f"{field}.springs.max_neighbors", integer=True)
    y = d.get("spring_Y")
    if y is None:
        if "spring_Y" not in arrays:
            r.fail(f"{field}.spring_Y", "null needs per-spring 'spring_Y' in the object's npz")
        kw["spring_Y"] = arrays["spring_Y"]
    else:
        kw["spring_Y"] = r.number(y, f"{field}.spring_Y")
    mass = d.get("mass", 1.0)
    if mass is None:
        if "masses" not in arrays:
            r.fail(f"{field}.mass", "null needs per-particle 'masses' in the object's npz")
        kw["mass"] = arrays["masses"]
    else:
        kw["mass"] = r.number(mass, f"{field}.mass")
    if d["binding"] not in ("rigid", "lbs"):
        r.fail(f"{field}.binding", f"expected 'rigid' or 'lbs', got {d['binding']!r}")
    kw["binding"] = d["binding"]
    kw["rest_pose"] = r.array(d["rest_pose"], f"{field}.rest_pose", (4, 4))
    kw["gaussians"] = r.gaussians(d.get("gaussians"), f"{field}.gaussians")
    kw["color_map"] = r.color_map(d.get("color_map"), f"{field}.color_map")
    kw["outline"] = _read_outline(r, d.get("outline"), f"{field}.outline")
    if d.get("goal_pose") is not None:
        kw["goal_pose"] = r.array(d["goal_pose"], f"{field}.goal_pose", (4, 4))
    return r.build(lambda: ObjectSpec(name, **kw), field)


def _color_map_json(cm: ColorMap | None):
    return None if cm is None else {"degree": int(cm.degree), "coeffs": cm.coeffs.tolist()}


def _write_object(obj: ObjectSpec, root: Path, prefix: str) -> dict:
    arrays = {"particles": np.asarray(obj.particles)}
    spring_y = np.asarray(obj.spring_Y)
    mass = np.asarray(obj.mass)
    if obj.springs is not None:
        arrays["springs"] = np.asarray(obj.springs)
        if obj.rest_lengths is not None:
            arrays["rest_lengths"] = np.asarray(obj.rest_lengths)
    if spring_y.ndim:
        arrays["spring_Y"] = spring_y
    if mass.ndim:
        arrays["masses"] = mass
    (root / prefix).parent.mkdir(parents=True, exist_ok=True)
    np.savez(root / f"{prefix}.npz", **arrays)
    out = {
        "name": obj.name,
        "arrays": f"{prefix}.npz",
        "springs": "explicit"
        if obj.springs is not None
        else {"radius": float(obj.spring_radius), "max_neighbors": int(obj.max_neighbors)},
        "spring_Y": None if spring_y.ndim else float(spring_y),
        "mass": None if mass.ndim else float(mass),
        "gaussians": None,
        "binding": obj.binding,
        "rest_pose": np.asarray(obj.rest_pose).tolist(),
        "color_map": _color_map_json(obj.color_map),
        "outline": None
        if obj.outline is None
        else {"polygon": obj.outline.polygon.tolist(), "height": obj.outline.height},
        "goal_pose": None if obj.goal_pose is None else np.asarray(obj.goal_pose).tolist(),
    }
    if obj.gaussians is not None:
        save_gaussians(obj.gaussians, root / f"{prefix}.ply")
        out["gaussians"] = f"{prefix}.ply"
    return out


def save_object(obj: ObjectSpec, folder, sim: dict | None = None) -> Path:
    """Write a standalone object directory (object.json + arrays + Gaussians); `sim` holds the global
    SimParams fields the object was identified or trained with. Returns the object.json path."""
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    sim = dict(sim or {})
    unknown = sorted(set(sim) - {f.name for f in dataclasses.fields(SimParams)})
    if unknown:
        raise ValueError(f"sim: unknown SimParams field(s) {unknown}")
    doc = {
        "format": OBJECT_FORMAT,
        "version": VERSION,
        "object": _write_object(obj, root, obj.name),
        "sim": _jsonable(sim),
    }
    path = root / "object.json"
    path.write_text(json.dumps(doc, indent=1) + "\n")
    return path


def load_object(folder) -> tuple[ObjectSpec, dict]:
    """Read a standalone object directory -> (ObjectSpec, the SimParams fields it carries)."""
    root = Path(folder)
    r = _Reader(root, "object.json")
    doc = _check_header(r, _read_json(root / "object.json", "object"), OBJECT_FORMAT, {"object"}, {"sim"})
    obj = _read_object(r, doc["object"], "object")
    sim = doc.get("sim") or {}
    r.dataclass(SimParams, {k: v for k, v in sim.items()}, "sim")  # validates names and values
    return obj, dict(sim)


# ---------------------------------------------------------------------------------------------- twins
_ROBOT_FIELDS = (
    {"urdf"},
    {
        "ee_link",
        "contact_links",
        "gripper_joint",
        "gripper_open",
        "gripper_closed",
        "home_q",
        "gaussians",
        "scan_spacing",
        "tool_contact",
        "color_map",
        "tool_radius",
        "contact_mesh",
    },
)
_CAMERA_FIELDS = (
    {"name", "intrinsics", "pose"},
    {"sensor_size", "mount_link", "crop", "output_hw", "depth", "response"},
)
_COLLIDER_FIELDS = (
    {"name", "mesh", "pose"},
    {"restitution", "friction", "gaussians", "color_map", "channel"},
)


def _read_robot(r: _Reader, d) -> RobotSpec:
    d = r.section(d, "robot", *_ROBOT_FIELDS)
    kw: dict = {}
    urdf = d["urdf"]
    if isinstance(urdf, str) and urdf.startswith("builtin:"):
        kw["urdf"] = urdf
    else:
        kw["urdf"] = str(r.path(urdf, "robot.urdf"))
    for key in ("ee_link", "gripper_joint"):
        if d.get(key) is not None and not isinstance(d[key], str):
            r.fail(f"robot.{key}", f"expected a link/joint name or null, got {d[key]!r}")
        kw[key] = d.get(key)
    for key in ("gripper_open", "gripper_closed"):
        kw[key] = None if d.get(key) is None else r.number(d[key], f"robot.{key}")
    links = d.get("contact_links", [])
    if not isinstance(links, list) or not all(isinstance(x, str) for x in links):
        r.fail("robot.contact_links", f"expected a list of link names, got {links!r}")
    kw["contact_links"] = tuple(links)
    if d.get("home_q") is not None:
        kw["home_q"] = tuple(r.array(d["home_q"], "robot.home_q", (len(d["home_q"]),)).tolist())
    g = d.get("gaussians")
    if g is not None:
        g = r.section(g, "robot.gaussians", {"file", "labels", "links"}, {"q"})
        kw["gaussians"] = r.gaussians(g["file"], "robot.gaussians.file")
        kw["gaussian_labels"] = r.npz(g["labels"], "robot.gaussians.labels", ("labels",))["labels"]
        if not isinstance(g["links"], list) or not all(isinstance(x, str) for x in g["links"]):
            r.fail("robot.gaussians.links", "expected a list of link names")
        kw["gaussian_links"] = tuple(g["links"])
        if g.get("q") is not None:
            kw["gaussians_q"] = tuple(r.array(g["q"], "robot.gaussians.q", (len(g["q"]),)).tolist())
    if "scan_spacing" in d:
        kw["scan_spacing"] = r.number(d["scan_spacing"], "robot.scan_spacing")
    if d.get("tool_contact") is not None:
        c = r.section(d["tool_contact"], "robot.tool_contact", {"restitution", "friction"}, set())
        kw["tool_contact"] = r.build(
            lambda: ContactSpec(
                r.number(c["restitution"], "robot.tool_contact"),
                r.number(c["friction"], "robot.tool_contact"),
            ),
            "robot.tool_contact",
        )
    kw["color_map"] = r.color_map(d.get("color_map"), "robot.color_map")
    if d.get("tool_radius") is not None:
        kw["tool_radius"] = r.number(d["tool_radius"], "robot.tool_radius")
    if d.get("contact_mesh") is not None:
        kw["contact_mesh"] = d["contact_mesh"]
    return r.build(lambda: RobotSpec(**kw), "robot")


def _read_camera(r: _Reader, d, field: str) -> CameraSpec:
    d = r.section(d, field, *_CAMERA_FIELDS)
    name, field = r.name(d, field)
    kw: dict = {
        "intrinsics": tuple(r.array(d["intrinsics"], f"{field}.intrinsics", (4,)).tolist()),
        "pose": r.array(d["pose"], f"{field}.pose", (4, 4)),
    }
    if "sensor_size" in d:
        kw["sensor_size"] = tuple(int(v) for v in r.array(d["sensor_size"], f"{field}.sensor_size", (2,)))
    if "output_hw" in d:
        kw["output_hw"] = tuple(int(v) for v in r.array(d["output_hw"], f"{field}.output_hw", (2,)))
    if d.get("crop") is not None:
        kw["crop"] = tuple(r.array(d["crop"], f"{field}.crop", (4,)).tolist())
    if d.get("mount_link") is not None:
        if not isinstance(d["mount_link"], str):
            r.fail(f"{field}.mount_link", "expected a robot link name or null")
        kw["mount_link"] = d["mount_link"]
    if "depth" in d:
        if not isinstance(d["depth"], bool):
            r.fail(f"{field}.depth", f"expected true or false, got {d['depth']!r}")
        kw["depth"] = d["depth"]
    if d.get("response") is not None:
        kw["response"] = r.build(lambda: CameraResponse.from_dict(d["response"]), f"{field}.response")
    return r.build(lambda: CameraSpec(name, **kw), field)


def _read_collider(r: _Reader, d, field: str) -> ColliderSpec:
    d = r.section(d, field, *_COLLIDER_FIELDS)
    name, field = r.name(d, field)
    vertices, faces = r.mesh(d["mesh"], f"{field}.mesh")
    channel = d.get("channel")
    if channel is not None:
        channel = tuple(r.array(channel, f"{field}.channel", (3,)).tolist())
    contact = r.build(
        lambda: ContactSpec(
            r.number(d.get("restitution", 0.0), f"{field}.restitution"),
            r.number(d.get("friction", 0.5), f"{field}.friction"),
        ),
        field,
    )
    return r.build(
        lambda: ColliderSpec(
            name,
            vertices,
            faces,
            r.array(d["pose"], f"{field}.pose", (4, 4)),
            contact,
            r.gaussians(d.get("gaussians"), f"{field}.gaussians"),
            r.color_map(d.get("color_map"), f"{field}.color_map"),
            channel,
        ),
        field,
    )


def _list(r: _Reader, value, field: str) -> list:
    if not isinstance(value, list):
        r.fail(field, f"expected a JSON list, got {type(value).__name__}")
    return value


def load_twin(folder) -> TwinSpec:
    """Read and validate a twin directory -> TwinSpec (errors: TwinFormatError naming file and field)."""
    root = Path(folder)
    if not root.is_dir():
        raise TwinFormatError(f"{root}: not a directory; a twin directory holds twin.json and its files")
    r = _Reader(root, "twin.json")
    doc = _check_header(
        r,
        _read_json(root / "twin.json", "twin"),
        TWIN_FORMAT,
        {"name", "robot", "objects", "cameras"},
        {"background", "colliders", "sim", "controller", "render"},
    )
    if not isinstance(doc["name"], str):
        r.fail("name", "expected a string")
    robot = _read_robot(r, doc["robot"])
    objects = [_read_object(r, o, f"objects[{i}]") for i, o in enumerate(_list(r, doc["objects"], "objects"))]
    cameras = [_read_camera(r, c, f"cameras[{i}]") for i, c in enumerate(_list(r, doc["cameras"], "cameras"))]
    colliders = [
        _read_collider(r, c, f"colliders[{i}]")
        for i, c in enumerate(_list(r, doc.get("colliders", []), "colliders"))
    ]
    bg = r.section(doc.get("background") or {}, "background", set(), {"gaussians", "color_map"})
    render_cfg = r.section(doc.get("render") or {}, "render", set(), {"background"})
    kw = {}
    if "background" in render_cfg:
        kw["render_background"] = tuple(r.array(render_cfg["background"], "render.background", (3,)).tolist())
    spec = r.build(
        lambda: TwinSpec(
            name=doc["name"],
            robot=robot,
            objects=tuple(objects),
            cameras=tuple(cameras),
            background=r.gaussians(bg.get("gaussians"), "background.gaussians"),
            background_color_map=r.color_map(bg.get("color_map"), "background.color_map"),
            colliders=tuple(colliders),
            sim=r.dataclass(SimParams, doc.get("sim") or {}, "sim"),
            controller=r.dataclass(ControllerConfig, doc.get("controller") or {}, "controller"),
            **kw,
        ),
        "(top level)",
    )
    _check_robot_names(r, spec)
    return spec


def _check_robot_names(r: _Reader, spec: TwinSpec) -> None:
    """The robot links twin.json names outside the robot section (camera mounts, the Gaussians' links)
    exist in its URDF (read without meshes); the robot section's own names are checked by the loader."""
    from twinbench.robot.builtin import load_builtin_arm
    from twinbench.robot.model import load_robot

    tool = spec.robot.builtin_tool
    if tool:
        model = load_builtin_arm(tool, load_meshes=False)
    else:
        model = load_robot(spec.robot.urdf, load_meshes=False)
    names = model.link_names
    for i, cam in enumerate(spec.cameras):
        if cam.mount_link is not None and cam.mount_link not in names:
            r.fail(f"cameras[{i}].mount_link", f"{cam.mount_link!r} is not a link of the robot "
                                               f"{Path(model.urdf_path).name} (links: {names})")
    missing = [n for n in spec.robot.gaussian_links if n not in names]
    if missing:
        r.fail("robot.gaussians.links", f"{missing} are not links of the robot {Path(model.urdf_path).name} "
                                        f"(links: {names})")


def twin_dir_hash(folder) -> str:
    """SHA-256 (hex) of a twin directory's content: every file inside it (symlinks leaving it skipped),
    path and bytes, in path order. Equal hashes: the same twin, whatever the folder is called."""
    import hashlib

    root = Path(folder).resolve()
    if not root.is_dir():
        raise TwinFormatError(f"{root}: not a directory; a twin directory holds twin.json and its files")
    h = hashlib.sha256()
    for p in sorted(root.rglob("*")):
        if not p.is_file() or not p.resolve().is_relative_to(root):
            continue
        h.update(f"{p.relative_to(root).as_posix()}\0{p.stat().st_size}\0".encode())
        with p.open("rb") as f:
            for chunk in iter(lambda: f.read(1 << 20), b""):
                h.update(chunk)
    return h.hexdigest()



def _feed(h, value) -> None:
    """Feed `value` (dataclasses, dicts, sequences, arrays, scalars) into hash `h`, typed and delimited. A
    dataclass field added after hashes were first kept (metadata `hash_unless_default`) is left out at its
    default, so that what was built before hashes as it did (a resumed run's twin check)."""
    if dataclasses.is_dataclass(value):
        h.update(f"<{type(value).__name__}".encode())
        for f in dataclasses.fields(value):
            if f.metadata.get("hash_unless_default") and getattr(value, f.name) == f.default:
                continue
            h.update(f"{f.name}=".encode())
            _feed(h, getattr(value, f.name))
        h.update(b">")
    elif isinstance(value, dict):
        h.update(f"{{{len(value)}".encode())
        for k in sorted(value, key=str):
            _feed(h, k)
            _feed(h, value[k])
    elif isinstance(value, list | tuple):
        h.update(f"[{len(value)}".encode())
        for v in value:
            _feed(h, v)
    elif isinstance(value, np.ndarray):
        a = np.ascontiguousarray(value)
        h.update(f"a{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes() if a.dtype != object else repr(a.tolist()).encode())
    else:  # None, bool, int, float, str, numpy scalars: their repr is exact
        h.update(f"{type(value).__name__}:{value!r};".encode())


def twin_spec_hash(spec: TwinSpec) -> str:
    """SHA-256 (hex) of a TwinSpec's data as it is built: every field (arrays by dtype, shape and bytes),
    and the bytes of the robot's URDF and the meshes it references (a built-in robot's from its assets).
    A built-in cell whose code changed what it builds hashes differently."""
    return _spec_digest(spec, spec.robot)


def twin_physics_hash(spec: TwinSpec) -> str:
    """`twin_spec_hash` of what simulation reads of `spec`: not its name, cameras, Gaussian clouds, colour
    maps or render background. Equal for twins that differ only in appearance (e.g. with and without colour
    alignment): an episode that renders no camera runs the same in both."""
    look = {"gaussians": None, "color_map": None}
    robot = dataclasses.replace(spec.robot, gaussian_labels=None, gaussian_links=(), gaussians_q=None, **look)
    return _spec_digest(("physics", robot, tuple(dataclasses.replace(o, **look) for o in spec.objects),
                         tuple(dataclasses.replace(c, **look) for c in spec.colliders), spec.sim,
                         spec.controller), spec.robot)


def _spec_digest(data, robot: RobotSpec) -> str:
    """SHA-256 of `data` (`_feed`) and of `robot`'s URDF and mesh files."""
    import hashlib

    from twinbench.robot.builtin import ASSETS
    from twinbench.robot.model import urdf_mesh_files

    h = hashlib.sha256()
    _feed(h, data)
    tool = robot.builtin_tool
    urdf = ASSETS / f"xarm7_{tool}.urdf" if tool is not None else Path(robot.urdf)
    files = [urdf, urdf.with_suffix(".json")] if tool is not None else [urdf]
    for path in files + sorted(p for _, p in urdf_mesh_files(urdf)):
        h.update(f"{path.name}\0{path.stat().st_size}\0".encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def _jsonable(value):
    if dataclasses.is_dataclass(value):
        return {f.name: _jsonable(getattr(value, f.name)) for f in dataclasses.fields(value)}
    if isinstance(value, dict):
        return {k: _jsonable(v) for k, v in value.items()}
    if isinstance(value, list | tuple | np.ndarray):
        return [_jsonable(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


def _robot_json(spec: RobotSpec, root: Path) -> dict:
    out = {
        "urdf": spec.urdf,
        "ee_link": spec.ee_link,
        "contact_links": list(spec.contact_links),
        "gripper_joint": spec.gripper_joint,
        "gripper_open": spec.gripper_open,
        "gripper_closed": spec.gripper_closed,
        "home_q": None if spec.home_q is None else list(spec.home_q),
        "gaussians": None,
        "scan_spacing": spec.scan_spacing,
        "tool_contact": _jsonable(spec.tool_contact),
        "color_map": _color_map_json(spec.color_map),
        "tool_radius": spec.tool_radius,
    }
    if spec.contact_mesh != "collision":  # written only when set, so that other twins stay readable as before
        out["contact_mesh"] = spec.contact_mesh
    if spec.builtin_tool is None:
        src = Path(spec.urdf).resolve()
        if src.is_relative_to(root.resolve()):
            out["urdf"] = src.relative_to(root.resolve()).as_posix()
        else:  # copy the URDF and the meshes it references (nothing else of its folder)
            _copy_urdf(src, root / "robot")
            out["urdf"] = f"robot/{src.name}"
    if spec.gaussians is not None:
        (root / "robot").mkdir(exist_ok=True)
        save_gaussians(spec.gaussians, root / "robot" / "gaussians.ply")
        np.savez(root / "robot" / "labels.npz", labels=np.asarray(spec.gaussian_labels, np.int32))
        out["gaussians"] = {
            "file": "robot/gaussians.ply",
            "labels": "robot/labels.npz",
            "links": list(spec.gaussian_links),
            "q": None if spec.gaussians_q is None else list(spec.gaussians_q),
        }
    return out


def _copy_urdf(src: Path, dest: Path) -> None:
    """Copy a URDF and each mesh it references to `dest`, where the copy finds them as the original does:
    a relative path at the same place under `dest`, package://PKG/REL at `dest`/PKG/REL."""
    from twinbench.robot.model import urdf_mesh_files

    dest.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(src, dest / src.name)
    for name, path in urdf_mesh_files(src):
        if name.startswith("package://"):
            rel = Path(name[len("package://"):])
        elif path.resolve().is_relative_to(src.parent):
            rel = path.resolve().relative_to(src.parent)
        else:  # an absolute path the copy still reads where it is
            continue
        (dest / rel).parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(path, dest / rel)


def _write_mesh(vertices, faces, path: Path) -> None:
    """A Wavefront .obj with shortest round-trip float text (read back bit for bit)."""
    lines = ["# twinbench collider mesh"]
    lines += [f"v {x!r} {y!r} {z!r}" for x, y, z in np.asarray(vertices, np.float64).tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in np.asarray(faces, np.int64).tolist()]
    path.write_text("\n".join(lines) + "\n")


def save_twin(spec: TwinSpec, folder) -> Path:
    """Write `spec` as a twin directory (created if needed; files of the same names are replaced).
    Returns the twin.json path."""
    root = Path(folder)
    root.mkdir(parents=True, exist_ok=True)
    doc: dict = {
        "format": TWIN_FORMAT,
        "version": VERSION,
        "name": spec.name,
        "robot": _robot_json(spec.robot, root),
        "background": {"gaussians": None, "color_map": _color_map_json(spec.background_color_map)},
    }
    if spec.background is not None:
        save_gaussians(spec.background, root / "background.ply")
        doc["background"]["gaussians"] = "background.ply"
    doc["objects"] = [_write_object(o, root, f"objects/{o.name}") for o in spec.objects]
    colliders = []
    for c in spec.colliders:
        (root / "colliders").mkdir(exist_ok=True)
        _write_mesh(c.vertices, c.faces, root / "colliders" / f"{c.name}.obj")
        entry = {
            "name": c.name,
            "mesh": f"colliders/{c.name}.obj",
            "pose": c.pose.tolist(),
            "restitution": c.contact.restitution,
            "friction": c.contact.friction,
            "gaussians": None,
            "color_map": _color_map_json(c.color_map),
            "channel": None if c.channel is None else list(c.channel),
        }
        if c.gaussians is not None:
            save_gaussians(c.gaussians, root / "colliders" / f"{c.name}.ply")
            entry["gaussians"] = f"colliders/{c.name}.ply"
        colliders.append(entry)
    doc["colliders"] = colliders
    doc["cameras"] = [
        {
            "name": c.name,
            "intrinsics": list(c.intrinsics),
            "pose": c.pose.tolist(),
            "sensor_size": list(c.sensor_size),
            "mount_link": c.mount_link,
            "crop": None if c.crop is None else list(c.crop),
            "output_hw": list(c.output_hw),
            "depth": c.depth,
            **({} if c.response is None else {"response": c.response.to_dict()}),
        }
        for c in spec.cameras
    ]
    doc["sim"] = _jsonable(spec.sim)
    doc["controller"] = _jsonable(spec.controller)
    doc["render"] = {"background": list(spec.render_background)}
    path = root / "twin.json"
    path.write_text(json.dumps(_jsonable(doc), indent=1) + "\n")
    return path
