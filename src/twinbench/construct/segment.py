"""Segment a workcell scan into robot / background / named objects with oriented crop boxes (DESIGN §1
step 2). No GUI: the user writes the boxes (and an optional coarse transform) in a JSON file.

boxes.json:
    {"transform": 4x4 | null,                 # scan -> coarse world, applied to the scan first
     "robot": BOX | [BOX, ...],               # the robot's Gaussians (union of boxes)
     "objects": {"tblock": BOX | [BOX, ...]}, # each object's Gaussians
     "bounds": BOX | [BOX, ...] | null}       # the background keeps only what lies inside (null: all)
    BOX = {"center": [x, y, z], "half_extents": [hx, hy, hz],
           "rotation": 3x3 box-to-frame | null, "rpy_deg": [roll, pitch, yaw] | null}

Objects claim their Gaussians first (in file order), then the robot; the background is the rest
(inside `bounds`); what is left is dropped.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twinbench.errors import check_name
from twinbench.gaussians.cloud import GaussianCloud


@dataclass(frozen=True)
class CropBox:
    center: np.ndarray  # (3,)
    rotation: np.ndarray  # (3, 3) box -> frame
    half_extents: np.ndarray  # (3,)

    def mask(self, cloud: GaussianCloud) -> np.ndarray:
        return cloud.box_mask(self.center, self.rotation, self.half_extents)


@dataclass
class Segments:
    """Index arrays into the (transformed) scan, one per part, and the transform applied."""

    transform: np.ndarray
    robot: np.ndarray
    background: np.ndarray
    objects: dict[str, np.ndarray]
    dropped: np.ndarray


def _rpy_matrix(rpy_deg) -> np.ndarray:
    r, p, y = np.radians(np.asarray(rpy_deg, dtype=np.float64))
    cx, sx, cy, sy, cz, sz = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _box(d, where: str) -> CropBox:
    if not isinstance(d, dict):
        raise ValueError(f"{where}: expected a box object {{center, half_extents, rotation|rpy_deg}}")
    unknown = set(d) - {"center", "half_extents", "rotation", "rpy_deg"}
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {sorted(unknown)}")
    try:
        c = np.asarray(d["center"], dtype=np.float64).reshape(3)
        h = np.asarray(d["half_extents"], dtype=np.float64).reshape(3)
    except (KeyError, ValueError, TypeError) as exc:
        raise ValueError(f"{where}: needs 'center' and 'half_extents', 3 numbers each ({exc})") from exc
    if np.any(h <= 0) or not np.all(np.isfinite(np.r_[c, h])):
        raise ValueError(f"{where}.half_extents: must be finite and > 0, got {h.tolist()}")
    if d.get("rotation") is not None and d.get("rpy_deg") is not None:
        raise ValueError(f"{where}: give 'rotation' or 'rpy_deg', not both")
    if d.get("rotation") is not None:
        r = np.asarray(d["rotation"], dtype=np.float64)
        if r.shape != (3, 3) or not np.allclose(r @ r.T, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
            raise ValueError(f"{where}.rotation: expected a 3x3 rotation matrix")
    elif d.get("rpy_deg") is not None:
        r = _rpy_matrix(d["rpy_deg"])
    else:
        r = np.eye(3)
    return CropBox(c, r, h)


def _boxes(value, where: str) -> list[CropBox]:
    if value is None:
        return []
    items = value if isinstance(value, list) else [value]
    return [_box(b, f"{where}[{i}]") for i, b in enumerate(items)]


def load_boxes(
    path,
) -> tuple[np.ndarray | None, list[CropBox], dict[str, list[CropBox]], list[CropBox] | None]:
    """Read boxes.json -> (transform or None, robot boxes, {object: boxes}, bounds boxes or None)."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{path}: cannot read the boxes JSON ({exc})") from exc
    if not isinstance(doc, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level")
    unknown = set(doc) - {"transform", "robot", "objects", "bounds"}
    if unknown:
        raise ValueError(
            f"{path}: unknown field(s) {sorted(unknown)}; known: transform, robot, objects, bounds"
        )
    t = doc.get("transform")
    if t is not None:
        t = np.asarray(t, dtype=np.float64)
        if t.shape != (4, 4) or not np.all(np.isfinite(t)):
            raise ValueError(f"{path}: transform must be a finite 4x4 matrix")
    objects = doc.get("objects") or {}
    if not isinstance(objects, dict):
        raise ValueError(f"{path}: objects must map names to boxes")
    for name in objects:  # each names a file <name>.ply
        check_name(name, f"{path}: objects: name")
    try:
        robot = _boxes(doc.get("robot"), "robot")
        objs = {name: _boxes(b, f"objects.{name}") for name, b in objects.items()}
        bounds = _boxes(doc.get("bounds"), "bounds") if doc.get("bounds") is not None else None
    except ValueError as exc:
        raise ValueError(f"{path}: {exc}") from exc
    return t, robot, objs, bounds


def segment_scan(
    cloud: GaussianCloud,
    robot: list[CropBox],
    objects: dict[str, list[CropBox]] | None = None,
    bounds: list[CropBox] | None = None,
    transform: np.ndarray | None = None,
) -> tuple[GaussianCloud, Segments]:
    """Apply the coarse transform, then split (see the module docstring). Returns the transformed
    scan and the index arrays into it."""
    t = np.eye(4) if transform is None else np.asarray(transform, dtype=np.float64)
    scan = cloud if transform is None else cloud.transform(t)
    free = np.ones(len(scan), bool)
    parts: dict[str, np.ndarray] = {}
    for name, boxes in (objects or {}).items():
        m = np.zeros(len(scan), bool)
        for b in boxes:
            m |= b.mask(scan)
        m &= free
        parts[name] = np.flatnonzero(m)
        free &= ~m
    rm = np.zeros(len(scan), bool)
    for b in robot:
        rm |= b.mask(scan)
    rm &= free
    free &= ~rm
    if bounds is not None:
        inside = np.zeros(len(scan), bool)
        for b in bounds:
            inside |= b.mask(scan)
    else:
        inside = np.ones(len(scan), bool)
    bg = free & inside
    return scan, Segments(t, np.flatnonzero(rm), np.flatnonzero(bg), parts, np.flatnonzero(free & ~inside))


def segment_files(scan_path, boxes_path, out) -> dict[str, int]:
    """`twinbench segment`: split the scan file by the boxes file and write OUT/robot.ply, background.ply,
    objects/NAME.ply, segments.npz (the index arrays) and segments.json; returns the count per part."""
    from twinbench.construct._json import write_json
    from twinbench.gaussians.io import load_gaussians, save_gaussians

    transform, robot, objects, bounds = load_boxes(boxes_path)
    scan, seg = segment_scan(load_gaussians(scan_path), robot, objects, bounds, transform)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    files = {"robot": "robot.ply", "background": "background.ply"}
    save_gaussians(scan.subset(seg.robot), out / "robot.ply")
    save_gaussians(scan.subset(seg.background), out / "background.ply")
    arrays = {"robot": seg.robot, "background": seg.background, "dropped": seg.dropped}
    for name, idx in seg.objects.items():
        check_name(name, "objects: name")
        files[name] = f"objects/{name}.ply"
        (out / "objects").mkdir(exist_ok=True)
        save_gaussians(scan.subset(idx), out / files[name])
        arrays[f"object_{name}"] = idx
    np.savez(out / "segments.npz", **arrays)
    counts = {k: int(len(v)) for k, v in arrays.items()}
    write_json(out / "segments.json", {"scan": str(scan_path), "transform": seg.transform.tolist(),
                                       "files": files, "counts": counts})
    return counts
