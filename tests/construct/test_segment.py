"""segment: oriented crop boxes split a scan into robot / objects / background after a coarse transform."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twinbench.cli import main as cli
from twinbench.construct.segment import load_boxes, segment_scan
from twinbench.gaussians.io import load_gaussians, save_gaussians
from twinbench.gaussians.primitives import surface_discs
from twinbench.transforms import rotvec_to_matrix


def _scene():
    rng = np.random.default_rng(0)
    robot = rng.uniform([-0.1, -0.1, 0.05], [0.1, 0.1, 0.6], (500, 3))
    block = rng.uniform([0.4, -0.05, 0.005], [0.5, 0.05, 0.03], (200, 3))
    table = np.c_[rng.uniform([-0.3, -0.5], [0.9, 0.5], (800, 2)), np.zeros(800)]
    far = rng.uniform(3, 4, (50, 3))
    pts = np.concatenate([robot, block, table, far])
    truth = np.repeat([0, 1, 2, 3], [500, 200, 800, 50])
    cloud = surface_discs(pts, np.tile([0, 0, 1.0], (len(pts), 1)), np.full((len(pts), 3), 0.5), 0.003)
    return cloud, truth


def test_boxes_split_the_scan_after_the_coarse_transform(tmp_path):
    cloud, truth = _scene()
    world_to_scan = np.eye(4)
    world_to_scan[:3, :3] = rotvec_to_matrix(np.array([0.2, -0.4, 1.0]))
    world_to_scan[:3, 3] = [1.0, 2.0, -0.5]
    scan = cloud.transform(world_to_scan)
    boxes = {
        "transform": np.linalg.inv(world_to_scan).tolist(),
        "robot": [{"center": [0, 0, 0.33], "half_extents": [0.12, 0.12, 0.3]}],
        "objects": {"block": {"center": [0.45, 0, 0.02], "half_extents": [0.06, 0.06, 0.017],
                              "rpy_deg": [0, 0, 10]}},
        "bounds": {"center": [0.3, 0, 0], "half_extents": [0.7, 0.7, 1.0]},
    }
    (tmp_path / "boxes.json").write_text(json.dumps(boxes))
    t, robot, objects, bounds = load_boxes(tmp_path / "boxes.json")
    moved, seg = segment_scan(scan, robot, objects, bounds, t)
    np.testing.assert_allclose(moved.means, cloud.means, atol=1e-5)
    assert set(seg.robot) == set(np.flatnonzero(truth == 0))
    assert set(seg.objects["block"]) == set(np.flatnonzero(truth == 1))
    assert set(seg.background) == set(np.flatnonzero(truth == 2))
    assert set(seg.dropped) == set(np.flatnonzero(truth == 3))
    # the command writes the same split
    save_gaussians(scan, tmp_path / "scan.ply")
    assert cli(["segment", str(tmp_path / "scan.ply"), "--boxes", str(tmp_path / "boxes.json"),
                "--out", str(tmp_path / "seg")]) == 0
    assert len(load_gaussians(tmp_path / "seg/objects/block.ply")) == 200
    with np.load(tmp_path / "seg/segments.npz") as z:
        np.testing.assert_array_equal(z["robot"], seg.robot)


def test_bad_boxes_are_named(tmp_path):
    p = tmp_path / "b.json"
    p.write_text(json.dumps({"robot": {"center": [0, 0, 0], "half_extents": [0.1, -1, 0.1]}}))
    with pytest.raises(ValueError, match=r"robot\[0\].half_extents"):
        load_boxes(p)
    p.write_text(json.dumps({"robots": {}}))
    with pytest.raises(ValueError, match="unknown field"):
        load_boxes(p)
