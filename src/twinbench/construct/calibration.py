"""Camera calibration import: intrinsics, camera-to-world (robot base) extrinsics and the wrist camera's
hand-eye transform, from a JSON (or YAML, with PyYAML installed) file -> `CameraSpec`s.

    {"base_to_world": 4x4 | null,        # when extrinsics are in another world frame (e.g. a marker's)
     "cameras": [
       {"name": "front", "intrinsics": [fx, fy, cx, cy] | "K": 3x3, "sensor_size": [w, h],
        "camera_to_world": 4x4 | "world_to_camera": 4x4,
        "axes": "opencv" | "opengl",       # OpenGL/Blender poses (y up, z back) are converted
        "output_hw": [240, 240], "crop": null},
       {"name": "wrist", "K": 3x3, "sensor_size": [848, 480],
        "hand_eye": 4x4, "mount_link": "link7"}   # camera pose in the mount link's frame
     ]}

The twin's world frame is the robot base frame: with `base_to_world`, poses become
inv(base_to_world) @ camera_to_world. `calibration_doc` writes camera specs back in this format (robot base
frame, OpenCV axes).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from twinbench.errors import check_name
from twinbench.twin.spec import CameraSpec

OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
_FIELDS = {"name", "intrinsics", "K", "sensor_size", "camera_to_world", "world_to_camera", "hand_eye",
           "mount_link", "axes", "output_hw", "crop", "depth"}


def _read_doc(path: Path) -> dict:
    text = path.read_text()
    if path.suffix.lower() in (".yaml", ".yml"):
        try:
            import yaml
        except ModuleNotFoundError as exc:
            raise ModuleNotFoundError(
                f"{path}: reading YAML needs PyYAML (pip install pyyaml), or write the file as JSON"
            ) from exc
        doc = yaml.safe_load(text)
    else:
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise ValueError(f"{path}: not valid JSON ({exc})") from exc
    if not isinstance(doc, dict) or not isinstance(doc.get("cameras"), list) or not doc["cameras"]:
        raise ValueError(f"{path}: expected an object with a non-empty 'cameras' list")
    return doc


def _matrix(value, shape, where: str) -> np.ndarray:
    try:
        m = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        m = np.zeros((0,))
    if m.shape != shape or not np.all(np.isfinite(m)):
        raise ValueError(f"{where}: expected {'x'.join(map(str, shape))} finite numbers, got {value!r:.80}")
    return m


def _rigid(m: np.ndarray, where: str) -> np.ndarray:
    r = m[:3, :3]
    if not np.allclose(r @ r.T, np.eye(3), atol=1e-5) or np.linalg.det(r) < 0:
        raise ValueError(f"{where}: the 3x3 block is not a rotation (orthonormalise it, or check the axes)")
    out = m.copy()
    u, _, vt = np.linalg.svd(r)
    out[:3, :3] = u @ vt  # remove round-off of files written with few digits
    return out


def load_calibration(path) -> list[CameraSpec]:
    """Camera specs (world = robot base frame) from a calibration file (see the module docstring)."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"calibration file not found: {path}")
    doc = _read_doc(path)
    b2w = np.eye(4)
    if doc.get("base_to_world") is not None:
        where = f"{path}: base_to_world"
        b2w = _rigid(_matrix(doc["base_to_world"], (4, 4), where), where)
    out = []
    for i, c in enumerate(doc["cameras"]):
        where = f"{path}: cameras[{i}]"
        if not isinstance(c, dict) or "name" not in c:
            raise ValueError(f"{where}: expected an object with a 'name'")
        check_name(c["name"], f"{where}.name")  # it names image files (align-color)
        where = f"{path}: cameras[{c['name']!r}]"
        unknown = set(c) - _FIELDS
        if unknown:
            raise ValueError(f"{where}: unknown field(s) {sorted(unknown)}; known: {sorted(_FIELDS)}")
        if ("intrinsics" in c) == ("K" in c):
            raise ValueError(f"{where}: give exactly one of 'intrinsics' [fx, fy, cx, cy] or 'K' (3x3)")
        if "K" in c:
            k = _matrix(c["K"], (3, 3), f"{where}.K")
            intr = (k[0, 0], k[1, 1], k[0, 2], k[1, 2])
        else:
            intr = tuple(float(v) for v in _matrix(c["intrinsics"], (4,), f"{where}.intrinsics"))
        axes = c.get("axes", "opencv")
        if axes not in ("opencv", "opengl"):
            raise ValueError(f"{where}.axes: expected 'opencv' or 'opengl', got {axes!r}")
        mount = c.get("mount_link")
        given = [k for k in ("camera_to_world", "world_to_camera", "hand_eye") if k in c]
        if len(given) != 1:
            raise ValueError(f"{where}: give exactly one of camera_to_world, world_to_camera, hand_eye")
        m = _matrix(c[given[0]], (4, 4), f"{where}.{given[0]}")
        if given[0] == "hand_eye":
            if not mount:
                raise ValueError(f"{where}: a hand_eye pose needs 'mount_link' (the link it is measured in)")
            pose = _rigid(m, f"{where}.hand_eye")
        else:
            if mount:
                raise ValueError(f"{where}: mount_link goes with hand_eye, not with {given[0]}")
            pose = _rigid(m, f"{where}.{given[0]}")
            if given[0] == "world_to_camera":
                pose = np.linalg.inv(pose)
            pose = np.linalg.inv(b2w) @ pose
        if axes == "opengl":
            pose = pose @ OPENGL_TO_OPENCV
        kw = {}
        for key, n in (("sensor_size", 2), ("output_hw", 2), ("crop", 4)):
            if c.get(key) is not None:
                v = _matrix(c[key], (n,), f"{where}.{key}")
                if key != "crop" and not np.all((v == np.round(v)) & (v >= 1)):
                    raise ValueError(f"{where}.{key}: expected 2 whole pixel counts >= 1, got {c[key]!r:.80}")
                kw[key] = tuple(int(x) for x in v) if key != "crop" else tuple(float(x) for x in v)
        try:
            depth = bool(c.get("depth", False))
            out.append(CameraSpec(str(c["name"]), intr, pose, mount_link=mount, depth=depth, **kw))
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from exc
    return out


def calibration_doc(cameras) -> dict:
    """The calibration file's content (robot base frame, OpenCV axes) of camera specs: what
    `load_calibration` reads back as the same specs."""
    docs = []
    for c in cameras:
        d = {"name": c.name, "intrinsics": [float(v) for v in c.intrinsics],
             "sensor_size": list(c.sensor_size), "output_hw": list(c.output_hw),
             "crop": None if c.crop is None else list(c.crop)}
        if c.mount_link is None:
            d["camera_to_world"] = np.asarray(c.pose).tolist()
        else:
            d.update(hand_eye=np.asarray(c.pose).tolist(), mount_link=c.mount_link)
        if c.depth:
            d["depth"] = True
        docs.append(d)
    return {"cameras": docs}
