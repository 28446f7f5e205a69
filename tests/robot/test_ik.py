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
