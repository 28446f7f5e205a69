"""Arms from example-robot-data (extra `xarm`) as a user brings them: Franka Panda (a URDF that xacro
generated), UR5, LeRobot's SO-100 / SO-101 (meshes named through another package's path), Unitree Z1
(a revolute jaw): each loads, picks the end effector a user expects, and IK reaches poses it can reach."""

from __future__ import annotations

import importlib.metadata

import numpy as np
import pytest

from twinbench.robot.ik import random_configurations, solve_ik
from twinbench.robot.model import load_robot

try:
    _DIST = importlib.metadata.distribution("example-robot-data")
except importlib.metadata.PackageNotFoundError:
    pytest.skip("example-robot-data is not installed (pip install 'twinbench[xarm]')",
                allow_module_level=True)

ROBOTS = _DIST.locate_file("cmeel.prefix/share/example-robot-data/robots")

# (URDF, gripper joint, end effector, arm joints, load meshes)
ARMS = [
    ("panda_description/urdf/panda.urdf", "panda_finger_joint1", "panda_hand_tcp", 7, True),
    ("ur_description/urdf/ur5_gripper.urdf", None, "ee_link", 6, False),
    ("so_arm_description/urdf/so101.urdf", "gripper", "gripper_frame_link", 5, True),
    ("so_arm_description/urdf/so100.urdf", "gripper", "gripper", 5, False),  # no frame link: the jaw's parent
    ("z1_description/urdf/z1.urdf", "jointGripper", "gripperStator", 6, False),
]


@pytest.mark.parametrize("urdf, gripper, ee, n_arm, meshes", ARMS, ids=[a[0].split("/")[-1] for a in ARMS])
def test_a_real_arm_loads_and_reaches_what_it_can_reach(urdf, gripper, ee, n_arm, meshes):
    model = load_robot(ROBOTS / urdf, gripper_joint=gripper, load_meshes=meshes)
    assert model.ee_link == ee and model.arm_q_indices.size == n_arm
    if meshes:  # every link with a <visual> mesh found it
        assert len(model.visual_meshes) >= n_arm + 1
        assert all(np.isfinite(m.vertices).all() and len(m.faces) for m in model.visual_meshes.values())
    if gripper is not None:
        k = model.joint_names.index(gripper)
        assert (model.gripper_open, model.gripper_closed) == (model.upper[k], model.lower[k])
    qs = random_configurations(model, 6, np.random.default_rng(0))
    result = solve_ik(model, model.ee_pose(qs))
    assert np.all(result.converged)
    np.testing.assert_allclose(model.ee_pose(result.q)[:, :3, 3], model.ee_pose(qs)[:, :3, 3], atol=1e-4)


def test_so101s_cad_gripper_and_jaw_collide_through_hulls_within_a_millimetre():
    """SO-101's gripper and jaw meshes (47,876 and 28,270 faces: CAD, too heavy to refit every substep)
    become hulls of at most 1,000 faces each, within a millimetre of their exact hulls."""
    links = ("gripper_link", "moving_jaw_so101_v1_link")
    urdf = ROBOTS / "so_arm_description/urdf/so101.urdf"
    model = load_robot(urdf, gripper_joint="gripper", contact_links=links)
    convex = model.with_convex_contacts()
    from twinbench.commands.robot_info import describe

    assert "(collision meshes over 5,000 faces: base_link, " in describe(model)  # robot-info says so
    for link in links:
        assert len(model.contact_faces(link)) > 20_000 and len(convex.contact_faces(link)) <= 1000
        assert 0 < convex.convex_contact_moved[link] < 0.001
        assert convex.collision_meshes[link].is_convex


def test_so101_points_a_tool_down_anywhere_in_its_reach_with_the_turn_about_the_vertical_free():
    """SO-101 (5 joints) pointing its gripper frame down on a 16 x 30 cm grid 2 cm above the table: with the
    whole orientation asked for, IK misses the whole centre line in front of it (y = 0, 23-42 mm short)
    and the far row; with the turn about the vertical free (what its planar controller asks) it reaches
    all but the far row's corners."""
    from twinbench.robot.ik import free_yaw_axis
    from twinbench.transforms import pose_matrix

    model = load_robot(ROBOTS / "so_arm_description/urdf/so101.urdf", gripper_joint="gripper")
    down = np.array([0.0, 1.0, 0.0, 0.0])
    xs, ys = (0.12, 0.16, 0.2, 0.24, 0.28), (-0.15, -0.075, 0.0, 0.075, 0.15)
    targets = np.stack([pose_matrix(np.array([x, y, 0.02]), down) for x in xs for y in ys])
    fixed = solve_ik(model, targets, model.home_q, restarts=4)
    free = solve_ik(model, targets, model.home_q, restarts=4, free_axis=free_yaw_axis(model, down))
    assert not fixed.converged.reshape(5, 5)[:, 2].any() and fixed.converged.sum() <= 16
    assert free.converged.reshape(5, 5)[:4].all() and free.converged.sum() >= 23
    ok = free.converged
    np.testing.assert_allclose(model.ee_pose(free.q[ok])[:, :3, 3], targets[ok, :3, 3], atol=1e-4)
