"""Velocity-control mimic: bounded joint speed, convergence, rest, gripper rate limit and force latch."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.robot.controller import ControllerConfig, RobotController
from twinbench.robot.ik import solve_ik
from twinbench.transforms import matrix_to_quat, pose_matrix, rotation_angle, rotvec_to_matrix

MAX_STEP = 0.1 * 0.15 / 0.02 / 30  # rad: clamp 0.10, v = dq / 0.02 * 0.15, q += v / 30


def _absolute(pose, gripper=0.0):
    return np.concatenate([pose[:3, 3], matrix_to_quat(pose[:3, :3]), [gripper]])


def test_far_target_bounded_joint_speed_then_converges(arm):
    ctrl = RobotController(arm)
    q_goal = arm.home_q + np.r_[0.9, 0.5, 0.0, 0.6, 0.3, -0.4, 0.8, 0.0]
    target = arm.ee_pose(q_goal)
    action = _absolute(target)
    deltas = []
    for _ in range(400):
        q_before = ctrl.q.copy()
        cmd = ctrl.step(action)
        d = np.linalg.norm(cmd.q[arm.arm_q_indices] - q_before[arm.arm_q_indices])
        deltas.append(d)
        np.testing.assert_array_equal(cmd.q_prev, q_before)
        np.testing.assert_allclose(cmd.joint_velocity, (cmd.q - q_before)[arm.arm_q_indices] * 30, atol=1e-12)
    deltas = np.array(deltas)
    assert deltas.max() <= MAX_STEP + 1e-12
    assert np.sum(deltas > MAX_STEP - 1e-9) > 20  # speed-limited phase at exactly the bound
    reached = ctrl.ee_pose()
    assert np.linalg.norm(reached[:3, 3] - target[:3, 3]) < 1e-3
    assert rotation_angle(reached[:3, :3], target[:3, :3]) < 1e-2


def test_step_applies_quarter_of_small_ik_delta(arm):
    # Within the clamp, one step moves 0.15 / 0.02 / 30 = 0.25 of the IK joint delta.
    ctrl = RobotController(arm)
    q_goal = arm.home_q + np.r_[0.01, -0.02, 0.0, 0.02, 0.0, 0.01, 0.0, 0.0]
    action = _absolute(arm.ee_pose(q_goal))
    ik = solve_ik(arm, arm.ee_pose(q_goal), arm.home_q, max_iters=60, restarts=4)
    cmd = ctrl.step(action)
    arm_idx = arm.arm_q_indices
    assert np.linalg.norm(ik.q[arm_idx] - arm.home_q[arm_idx]) < 0.1
    np.testing.assert_allclose(
        cmd.q[arm_idx] - arm.home_q[arm_idx], 0.25 * (ik.q - arm.home_q)[arm_idx], atol=1e-12
    )


def test_target_at_current_pose_stays_still(arm):
    ctrl = RobotController(arm)
    action = _absolute(ctrl.ee_pose(), gripper=0.0)
    for _ in range(10):
        cmd = ctrl.step(action)
    np.testing.assert_allclose(cmd.q, arm.home_q, atol=1e-12)
    assert np.abs(cmd.joint_velocity).max() < 1e-9


def test_gripper_rate_limit(arm):
    ctrl = RobotController(arm)
    hold = _absolute(ctrl.ee_pose())
    close = hold.copy()
    close[7] = 1.0
    values = [ctrl.step(close).gripper for _ in range(20)]
    expected = np.minimum(np.arange(1, 21) * 2 / 30, 1.0)
    np.testing.assert_allclose(values, expected, atol=1e-12)
    openings = ctrl.step(close).gripper_opening
    assert openings == pytest.approx(0.0)
    opened = [ctrl.step(hold).gripper for _ in range(3)]
    np.testing.assert_allclose(opened, [1 - 2 / 30, 1 - 4 / 30, 1 - 6 / 30], atol=1e-12)
    assert ctrl.step(hold).gripper_opening == pytest.approx(0.085 * (8 / 30), abs=1e-12)


def test_gripper_force_latch_closes_holds_and_releases(arm):
    cfg = ControllerConfig()
    ctrl = RobotController(arm, cfg)
    close = _absolute(ctrl.ee_pose(), gripper=1.0)
    hi, lo = 4e4, 1e3
    for _ in range(5):  # free closing
        cmd = ctrl.step(close, finger_forces=(0.0, 0.0))
    g_contact = cmd.gripper
    assert g_contact == pytest.approx(5 * 2 / 30)
    # one finger loaded only: keeps closing
    cmd = ctrl.step(close, finger_forces=(hi, lo))
    assert not cmd.latched and cmd.gripper == pytest.approx(g_contact + 2 / 30)
    held = cmd.gripper
    # both fingers above the threshold (3-vector forces accepted): latched, holds while commanded closed
    for _ in range(10):
        cmd = ctrl.step(close, finger_forces=(np.array([0.0, hi, 0.0]), np.array([0.0, -hi, 1.0])))
        assert cmd.latched and cmd.gripper == pytest.approx(held)
    # exactly at the threshold is not above it: closing resumes
    cmd = ctrl.step(close, finger_forces=(cfg.grasp_force_threshold, hi))
    assert not cmd.latched and cmd.gripper == pytest.approx(held + 2 / 30)
    # forces drop: released, closing continues
    cmd = ctrl.step(close, finger_forces=(lo, lo))
    assert not cmd.latched and cmd.gripper == pytest.approx(held + 4 / 30)
    # latched again, then the command opens: gripper opens at the rate limit despite the forces
    ctrl.step(close, finger_forces=(hi, hi))
    g = ctrl.gripper
    cmd = ctrl.step(_absolute(ctrl.ee_pose(), gripper=0.0), finger_forces=(hi, hi))
    assert cmd.gripper == pytest.approx(g - 2 / 30)


def test_relative_action_composes_with_current_pose(arm):
    ctrl = RobotController(arm, ControllerConfig(action_mode="relative"))
    start = ctrl.ee_pose()
    delta = np.array([0.02, -0.01, 0.03, 0.0, 0.0, 0.1, 0.0])
    target, g = ctrl.target_from_action(delta)
    np.testing.assert_allclose(target[:3, 3], start[:3, 3] + delta[:3])
    np.testing.assert_allclose(target[:3, :3], rotvec_to_matrix(delta[3:6]) @ start[:3, :3])
    assert g == 0.0
    # a zero delta keeps the robot still
    cmd = ctrl.step(np.zeros(7))
    np.testing.assert_allclose(cmd.q, arm.home_q, atol=1e-12)
    # repeated deltas move the end effector along +x; each frame tracks 0.25 of the delta (velocity
    # mimic: 0.15 / 0.02 / 30), so 30 frames of 2 mm move about 30 * 0.5 mm = 15 mm
    for _ in range(30):
        ctrl.step(np.array([0.002, 0, 0, 0, 0, 0, 0.0]))
    moved = ctrl.ee_pose()[:3, 3] - start[:3, 3]
    assert moved[0] == pytest.approx(0.015, abs=5e-4)
    assert abs(moved[1]) < 1e-4 and abs(moved[2]) < 1e-4


def test_planar_pushing_reaches_xy_at_fixed_height(pusher_arm):
    cfg = ControllerConfig(action_mode="planar", planar_height=0.03)
    ctrl = RobotController(pusher_arm, cfg)
    for _ in range(200):
        cmd = ctrl.step(np.array([0.45, 0.10]))
    ee = ctrl.ee_pose()
    np.testing.assert_allclose(ee[:3, 3], [0.45, 0.10, 0.03], atol=1e-3)
    assert rotation_angle(ee[:3, :3], pose_matrix(np.zeros(3), np.array(cfg.planar_quat))[:3, :3]) < 1e-2
    np.testing.assert_allclose(ctrl.ee_state(), [0.45, 0.10], atol=1e-3)
    assert cmd.gripper_opening == 0.0


def test_planar_pushing_with_a_four_joint_arm_leaves_the_turn_about_the_vertical_free(four_joint_arm):
    """A four-joint arm reaches planar targets pointing down, whatever turn the pan gives it there; before,
    the controller asked for the pushing orientation's own turn and stopped centimetres short."""
    cfg = ControllerConfig(action_mode="planar", planar_height=0.03)
    ctrl = RobotController(four_joint_arm, cfg)
    for target in ([0.2, 0.1], [0.15, -0.2]):
        for _ in range(150):
            cmd = ctrl.step(np.array(target))
        assert cmd.ik_converged
        np.testing.assert_allclose(ctrl.ee_pose()[:3, 3], [*target, 0.03], atol=1e-3)
        np.testing.assert_allclose(ctrl.ee_pose()[:3, 2], [0.0, 0.0, -1.0], atol=1e-3)
    ctrl.free_axis = None  # the whole orientation asked for: it cannot get there
    for _ in range(150):
        cmd = ctrl.step(np.array([0.2, 0.1]))
    assert not cmd.ik_converged and np.linalg.norm(ctrl.ee_pose()[:2, 3] - [0.2, 0.1]) > 0.005


def test_action_validation(arm):
    ctrl = RobotController(arm)
    with pytest.raises(ValueError, match="expected shape"):
        ctrl.step(np.zeros(7))
    bad = _absolute(ctrl.ee_pose())
    bad[1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        ctrl.step(bad)
    zero_quat = _absolute(ctrl.ee_pose())
    zero_quat[3:7] = 0
    with pytest.raises(ValueError, match="quaternion"):
        ctrl.step(zero_quat)
    with pytest.raises(ValueError, match="finger_forces"):
        ctrl.step(_absolute(ctrl.ee_pose()), finger_forces=(1.0,))
    with pytest.raises(ValueError, match="action_mode"):
        ControllerConfig(action_mode="joint")


def test_ee_state_observation(arm):
    ctrl = RobotController(arm)
    s = ctrl.ee_state()
    assert s.shape == (8,)
    np.testing.assert_allclose(s[:3], [0.35, 0.0, 0.25], atol=1e-6)
    assert abs(abs(s[4]) - 1.0) < 1e-6  # pointing down: quaternion +-(0, 1, 0, 0)
    assert s[7] == pytest.approx(0.0)  # home gripper is open


def test_unreachable_target_moves_toward_it_without_nan(arm):
    ctrl = RobotController(arm)
    start = ctrl.ee_pose()[:3, 3].copy()
    action = np.array([1.5, 0.0, 0.2, 0.0, 1.0, 0.0, 0.0, 0.0])
    for _ in range(60):
        q_before = ctrl.q.copy()
        cmd = ctrl.step(action)
        assert np.all(np.isfinite(cmd.q)) and not cmd.ik_converged
        assert np.linalg.norm((cmd.q - q_before)[arm.arm_q_indices]) <= MAX_STEP + 1e-12
    end = ctrl.ee_pose()[:3, 3]
    assert end[0] > start[0] + 0.15  # stretched toward x = 1.5 m
    assert np.all(ctrl.q >= arm.lower) and np.all(ctrl.q <= arm.upper)


def test_advance_worlds_gives_each_world_its_own_advance_bit_for_bit(arm):
    """One batched IK solve for many worlds: far, near, unreachable targets and gripper latches mixed."""
    ctrl = RobotController(arm)
    rng = np.random.default_rng(4)
    goals = [arm.ee_pose(arm.home_q + np.r_[rng.normal(0, 0.4, 7), 0.0]) for _ in range(5)]
    actions = [_absolute(g, gripper=float(i % 2)) for i, g in enumerate(goals)]
    actions.append(np.array([1.5, 0.0, 0.2, 0.0, 1.0, 0.0, 0.0, 1.0]))  # unreachable: restarts, cached
    forces = [None, (5e4, 5e4), (1.0, 2.0), None, (4e4, [3e4, 0, 0]), None]
    batch = [ctrl.initial_state() for _ in actions]
    alone = [ctrl.initial_state() for _ in actions]
    for _ in range(25):
        cmds = ctrl.advance_worlds(batch, actions, forces)
        for state, a, f, cmd in zip(alone, actions, forces, cmds, strict=True):
            ref = ctrl.advance(state, a, f)
            assert np.array_equal(ref.q, cmd.q) and np.array_equal(ref.joint_velocity, cmd.joint_velocity)
            flags = (cmd.gripper, cmd.latched, cmd.ik_converged)
            assert (ref.gripper, ref.latched, ref.ik_converged) == flags
    assert len({tuple(s.q.round(6)) for s in batch}) == len(actions)  # the worlds went different ways
    assert any(s.latched for s in batch) and batch[-1].restart_cache is not None
