"""Inverse kinematics: round trips from FK, unreachable targets, input validation."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.robot.ik import random_configurations, solve_ik
from twinbench.transforms import pose_matrix, rotation_angle


def test_ik_round_trip_200_random_reachable_poses(arm):
    rng = np.random.default_rng(42)
    q_true = random_configurations(arm, 200, rng)
    targets = arm.ee_pose(q_true)
    res = solve_ik(arm, targets, arm.home_q)  # warm start from home, far from most targets
    assert res.q.shape == (200, arm.n_q) and res.converged.shape == (200,)
    # Check with FK of the returned configurations, not the solver's own error report.
    reached = arm.ee_pose(res.q)
    pos_err = np.linalg.norm(reached[:, :3, 3] - targets[:, :3, 3], axis=1)
    rot_err = rotation_angle(reached[:, :3, :3], targets[:, :3, :3])
    assert pos_err.max() < 1e-3
    assert rot_err.max() < 1e-2
    assert res.converged.all()
    assert np.all(res.q >= arm.lower - 1e-12) and np.all(res.q <= arm.upper + 1e-12)
    # the gripper joint (not an arm joint) is copied from the warm start
    np.testing.assert_array_equal(res.q[:, 7], arm.home_q[7])


def test_ik_single_target_and_warm_start_stays_close(arm):
    q_near = arm.home_q + np.r_[0.05, -0.03, 0.02, 0.04, -0.05, 0.03, 0.02, 0.0]
    res = solve_ik(arm, arm.ee_pose(q_near), arm.home_q, restarts=0)
    assert res.q.shape == (arm.n_q,) and bool(res.converged)
    # a nearby target from a nearby warm start: the redundant arm stays in the same branch
    assert np.linalg.norm(res.q - q_near) < 0.2
    np.testing.assert_allclose(arm.ee_pose(res.q)[:3, 3], arm.ee_pose(q_near)[:3, 3], atol=1e-4)


def test_unreachable_target_returns_closest_solution_and_flag(arm):
    far = pose_matrix(np.array([2.0, 0.0, 0.5]), np.array([0.0, 1.0, 0.0, 0.0]))
    res = solve_ik(arm, np.stack([far, arm.ee_pose(arm.home_q)]), arm.home_q)
    assert res.converged.tolist() == [False, True]
    assert np.all(np.isfinite(res.q)) and np.all(np.isfinite(res.pos_err))
    assert np.all(res.q >= arm.lower) and np.all(res.q <= arm.upper)
    # Brute-force reference: the solver's weighted error is no worse than the best of 20,000 random
    # in-limit configurations (weights as in solve_ik: position m, rotation x 0.25).
    rng = np.random.default_rng(3)
    qs = random_configurations(arm, 20000, rng)
    ee = arm.ee_pose(qs)
    cost = (
        np.linalg.norm(ee[:, :3, 3] - far[:3, 3], axis=1) ** 2
        + (0.25 * rotation_angle(ee[:, :3, :3], far[:3, :3])) ** 2
    )
    got = res.pos_err[0] ** 2 + (0.25 * res.rot_err[0]) ** 2
    assert got <= cost.min() + 1e-6
    # the reported errors are the true ones
    reached = arm.ee_pose(res.q[0])
    assert res.pos_err[0] == pytest.approx(np.linalg.norm(reached[:3, 3] - far[:3, 3]), rel=1e-9)


def test_ik_input_validation(arm):
    with pytest.raises(ValueError, match="target"):
        solve_ik(arm, np.eye(3))
    bad = np.eye(4)
    bad[0, 3] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        solve_ik(arm, bad)
    skew = np.eye(4)
    skew[0, 1] = 0.5
    with pytest.raises(ValueError, match="rotation"):
        solve_ik(arm, skew)
    with pytest.raises(ValueError, match="batch"):
        solve_ik(arm, np.stack([np.eye(4)] * 3), np.zeros((2, arm.n_q)))


def test_a_free_axis_leaves_the_turn_about_it_free_and_measures_the_axis_angle(four_joint_arm, pusher_arm):
    """A four-joint arm cannot point its tool down with any turn about the vertical: the turn is the pan's,
    set by where the tool is. With the tool's axis free, pointing down at a place the pan does not face
    in the target's turn converges (position exact, the axis straight down); without, it cannot."""
    from twinbench.robot.ik import free_yaw_axis, pose_error

    arm = four_joint_arm
    down = np.array([0.0, 1.0, 0.0, 0.0])  # wxyz, tool z pointing down, its x along world x
    axis = free_yaw_axis(arm, down)
    np.testing.assert_allclose(axis, [0, 0, -1], atol=1e-12)  # the tool's z, pointing down
    targets = np.stack([pose_matrix(np.array(p), down) for p in [(0.2, 0.1, 0.05), (0.15, -0.2, 0.1),
                                                                   (0.25, 0.0, 0.02), (0.1, 0.15, 0.0)]])
    fixed = solve_ik(arm, targets, arm.home_q, restarts=4)
    free = solve_ik(arm, targets, arm.home_q, restarts=4, free_axis=axis)
    assert not fixed.converged[[0, 1, 3]].any()  # these need a turn the pan does not give there
    assert free.converged.all()
    reached = arm.ee_pose(free.q)
    np.testing.assert_allclose(reached[:, :3, 3], targets[:, :3, 3], atol=1e-4)
    np.testing.assert_allclose(reached[:, :3, 2], np.tile([0.0, 0.0, -1.0], (4, 1)), atol=1e-3)
    # the error it measures: none for a pure turn about the axis; a tilt's angle; pi for the axis reversed
    turned = pose_matrix(np.zeros(3), np.array([0.0, np.cos(0.4), np.sin(0.4), 0.0]))  # down, turned 0.8
    tilted = pose_matrix(np.zeros(3), down) @ pose_matrix(np.zeros(3), np.array([np.cos(0.15), np.sin(0.15),
                                                                                  0.0, 0.0]))  # tilted 0.3
    ee = np.stack([turned, tilted, np.eye(4)])
    err = pose_error(ee, np.stack([pose_matrix(np.zeros(3), down)] * 3), 1.0, axis)
    np.testing.assert_allclose(np.linalg.norm(err[:, 3:], axis=1), [0.0, 0.3, np.pi], atol=1e-9)
    assert free_yaw_axis(pusher_arm, down) is None  # seven joints hold any orientation: nothing is freed
