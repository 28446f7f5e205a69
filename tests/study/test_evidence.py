"""make_evidence: the scan, boxes, calibration, real images and tracked motion of a hidden workcell, in
the construction tools' formats, carrying the hidden values only as a user's evidence would."""

from __future__ import annotations

import json

import imageio.v3 as iio
import numpy as np
import pytest
from scipy.spatial import cKDTree

from twinbench.construct.calibration import load_calibration
from twinbench.construct.sysid_io import load_sysid_data
from twinbench.gaussians.io import load_gaussians
from twinbench.study.evidence import make_evidence
from twinbench.study.real import make_real, task_cell
from twinbench.transforms import invert_pose, rotation_angle, transform_points
from twinbench.twin import build_twin, load_twin


@pytest.fixture(scope="module")
def made(tmp_path_factory):
    root = tmp_path_factory.mktemp("study")
    real = make_real("push-t", 0, root / "REAL", "small")
    return real, make_evidence(real, root / "EV", seed=0, size="small")


def test_evidence_files_and_index(made):
    real, ev = made
    names = sorted(p.relative_to(ev).as_posix() for p in ev.rglob("*") if p.is_file())
    assert names == ["README.md", "boxes.json", "calibration.json", "evidence.json",
                     "motion/tblock-push/data.npz", "motion/tblock-push/sysid.json", "motion/tblock/data.npz",
                     "motion/tblock/sysid.json", "real/front.png", "scan.ply"]
    index = json.loads((ev / "evidence.json").read_text())
    assert index["task"] == "push-t" and index["objects"] == ["tblock"]
    assert index["push"] == {"tblock": "motion/tblock-push"}
    assert index["urdf"] == task_cell("push-t", "small").robot.urdf
    hidden = (real / "hidden.json").read_text()
    assert "factors" not in (ev / "README.md").read_text() and "hidden" not in json.dumps(index)
    assert hidden  # the hidden file stays in REAL/


def test_scan_is_the_real_scene_moved_recoloured_noisy(made):
    real, ev = made
    hidden = json.loads((real / "hidden.json").read_text())
    spec = load_twin(real / "world")
    scan = load_gaussians(ev / "scan.ply")
    world_pts = transform_points(invert_pose(np.asarray(hidden["scan"]["world_to_scan"])), scan.means)
    twin, _ = build_twin(spec)
    robot = twin.robot_gaussians.posed(twin.robot.home_q)
    reference = np.concatenate([robot.means, spec.background.means,
                                transform_points(spec.objects[0].rest_pose, spec.objects[0].gaussians.means)])
    d = cKDTree(reference).query(world_pts)[0]
    assert np.mean(d < 0.006) > 0.97  # in the scan frame, back in the world within the scan's noise
    assert 0.003 < np.mean(d > 0.05) < 0.02  # floaters, about 1 %
    assert len(scan) < 0.6 * len(reference)  # coarser than the real scene
    assert np.abs(scan.means - world_pts).max() > 0.05  # really in another frame


def test_calibration_has_realistic_error(made):
    real, ev = made
    spec = load_twin(real / "world")
    for cam in load_calibration(ev / "calibration.json"):
        truth = spec.camera(cam.name)
        angle = np.degrees(rotation_angle(cam.pose[:3, :3], truth.pose[:3, :3]))
        shift = np.linalg.norm(cam.pose[:3, 3] - truth.pose[:3, 3])
        assert 0.05 < angle < 0.5 and 0.0005 < shift < 0.005
        assert np.allclose(cam.intrinsics, truth.intrinsics, rtol=0.03)
    img = iio.imread(ev / "real/front.png")
    assert img.shape == (*spec.camera("front").output_hw, 3)


def test_tracked_motion_is_coarse_noisy_with_gaps(made):
    real, ev = made
    hidden = json.loads((real / "hidden.json").read_text())
    data = load_sysid_data(ev / "motion/tblock")
    assert data.validation_frames == 10 and data.tracked.shape[0] == 45
    # fewer particles than the real object (its layout is finer than any reconstruction's)
    assert len(data.particles) < 0.5 * hidden["object"]["particles"]
    # the probe lifted one end and dragged the object: tracks move by centimetres
    move = np.linalg.norm(data.tracked[-1] - data.tracked[0], axis=1)
    assert move.max() > 0.03
    lift = data.tracked[:, :, 2].max(axis=0) - data.tracked[0, :, 2]
    assert lift.max() > 0.025
    # occlusion gaps: runs of >= 4 frames without a valid track sample
    def longest_gap(valid) -> int:
        run = best = 0
        for v in valid:
            run = 0 if v else run + 1
            best = max(best, run)
        return best

    gaps = [longest_gap(data.motion_valid[:, j]) for j in range(data.motion_valid.shape[1])]
    assert sum(g >= 4 for g in gaps) >= len(gaps) // 5
    assert 0.6 < data.visibility.mean() < 0.8


def test_push_recording_holds_the_tool_and_its_path_not_its_friction(made):
    real, ev = made
    hidden = json.loads((real / "hidden.json").read_text())
    data = load_sysid_data(ev / "motion/tblock-push")
    spec = load_twin(real / "world")
    twin, _ = build_twin(spec)
    pusher = twin.robot.contact_vertices(twin.robot.home_q, "pusher")
    # the tool is the robot's pusher (home orientation), moved down to the table beside the T, then along
    assert data.has_tool and data.num_controls == 0
    np.testing.assert_allclose(data.tool_vertices, pusher)
    path = data.tool_path()
    assert abs(path[0, :, 2].min() - 0.005) < 0.003
    assert 0.07 < np.linalg.norm(data.tool_poses[-1, :3, 3] - data.tool_poses[0, :3, 3]) < 0.09
    # it pushed the T: tracks move by centimetres along the table, not up
    move = data.tracked[-1] - data.tracked[0]
    assert np.linalg.norm(move[:, :2], axis=1).max() > 0.03 and np.abs(move[:, 2]).max() < 0.01
    friction = hidden["tool_contact"]["friction"]
    assert str(round(friction, 6)) not in (ev / "motion/tblock-push/sysid.json").read_text()


def test_a_gripper_gets_no_push_recording(tmp_path):
    # a gripper's fingers hold by friction under the latch's force: a push would not show what a grasp needs
    real = make_real("rope-routing", 0, tmp_path / "REAL", "small")
    ev = make_evidence(real, tmp_path / "EV", seed=0, size="small")
    index = json.loads((ev / "evidence.json").read_text())
    assert index["push"] == {} and not (ev / "motion/rope-push").exists()
    assert "OBJECT-push" not in (ev / "README.md").read_text()
    assert not load_sysid_data(ev / "motion/rope").has_tool
