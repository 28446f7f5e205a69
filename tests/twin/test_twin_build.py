"""Scene: Gaussians follow the robot (FK) and the objects (rigid fit / LBS) in the device buffer."""

import numpy as np
import pytest

from twinbench.physics import SimParams
from twinbench.robot.builtin import load_builtin_arm
from twinbench.robot.controller import ControllerConfig
from twinbench.robot.gaussians import sample_robot_scan
from twinbench.robot.ik import solve_ik
from twinbench.scene.assets import surface_discs
from twinbench.scene.cameras import front_camera
from twinbench.scene.scene import ObjectSpec, Scene
from twinbench.transforms import planar_pose, transform_points
from twinbench.transforms import pose_matrix as ee_pose

N_OBJ_GAUSSIANS = 200


def _object(name: str, rigid: bool, spring_y: float) -> ObjectSpec:
    g = (np.arange(4) - 1.5) * 0.01
    pts = np.stack(np.meshgrid(g, g, g + 0.015, indexing="ij"), -1).reshape(-1, 3)
    rng = np.random.default_rng(0)
    means = rng.uniform(pts.min(0), pts.max(0), (N_OBJ_GAUSSIANS, 3)).astype(np.float32)
    cloud = surface_discs(means, np.tile([0.0, 0.0, 1.0], (N_OBJ_GAUSSIANS, 1)), (0.8, 0.2, 0.2), 0.004)
    return ObjectSpec(name, pts, cloud, rigid=rigid, spring_radius=0.018, spring_Y=spring_y)


@pytest.fixture(scope="module")
def setup():
    robot = load_builtin_arm("pusher")
    robot_gaussians = sample_robot_scan(robot, spacing=0.02)
    sim = SimParams(dt=1 / 30 / 300, substeps=300, ground_restitution=0.0, ground_friction=0.5,
                    object_collision=False, mesh_margin=0.006)
    static = surface_discs(np.zeros((1, 3), np.float32), np.array([[0.0, 0, 1]]), (0.5, 0.5, 0.5), 0.01)
    scene = Scene(robot, robot_gaussians, static, [_object("block", True, 3e4), _object("soft", False, 3e3)],
                  [front_camera()], sim=sim,
                  controller=ControllerConfig(action_mode="planar", planar_height=0.01))
    return scene, robot_gaussians


def _segments(scene, robot_gaussians) -> dict[str, np.ndarray]:
    means = scene.gaussians.means.numpy()
    a = 1 + len(robot_gaussians)
    return {"robot": means[1:a], "block": means[a:a + N_OBJ_GAUSSIANS], "soft": means[a + N_OBJ_GAUSSIANS:]}


def test_reset_places_robot_and_object_gaussians(setup):
    scene, robot_gaussians = setup
    poses = {"block": planar_pose(0.5, 0.1, 0.3), "soft": planar_pose(0.5, -0.1, -0.2)}
    scene.reset(None, poses)
    seg = _segments(scene, robot_gaussians)
    # device path (scene buffer) == host path (RobotGaussians.posed) at the same configuration
    np.testing.assert_allclose(seg["robot"], robot_gaussians.posed(scene.controller.q).means, atol=1e-5)
    for name in ("block", "soft"):
        rest = scene._objects[name].spec.gaussians.means.astype(np.float64)
        np.testing.assert_allclose(seg[name], transform_points(poses[name], rest), atol=1e-5)
        np.testing.assert_allclose(scene.object_pose(name), poses[name], atol=1e-6)


def test_pushed_block_carries_its_gaussians_rigidly(setup):
    scene, robot_gaussians = setup
    tip_down = ee_pose(np.array([0.35, 0.0, 0.01]), np.array([0.0, 1.0, 0.0, 0.0]))  # pusher at table height
    q0 = solve_ik(scene.robot, tip_down, scene.robot.home_q).q
    scene.reset(q0, {"block": planar_pose(0.45, 0.0, 0.0), "soft": planar_pose(0.3, -0.2, 0.0)})
    start = scene.controller.ee_state()
    for k in range(45):  # sweep the pusher through the block's position along +x
        scene.step(np.array([start[0] + 0.006 * (k + 1), 0.0]))
    pose = scene.object_pose("block")
    assert pose[0, 3] > 0.46  # pushed along +x
    seg = _segments(scene, robot_gaussians)
    rest = scene._objects["block"].spec.gaussians.means.astype(np.float64)
    np.testing.assert_allclose(seg["block"], transform_points(pose, rest), atol=1e-5)
    np.testing.assert_allclose(seg["robot"], robot_gaussians.posed(scene.controller.q).means, atol=1e-5)


def test_soft_object_gaussians_follow_its_particles(setup):
    scene, robot_gaussians = setup
    drop = planar_pose(0.3, -0.2, 0.4)
    drop[2, 3] = 0.03  # released 3 cm above the table: it falls, lands and squashes a little
    scene.reset(None, {"soft": drop, "block": planar_pose(0.6, 0.2, 0.0)})
    for _ in range(12):
        scene.step(scene.controller.ee_state())
    particles = scene.particles("soft")
    assert particles[:, 2].min() < 1e-3  # on the table
    means = _segments(scene, robot_gaussians)["soft"]
    lo, hi = particles.min(0), particles.max(0)
    assert np.all(means >= lo - 2e-3) and np.all(means <= hi + 2e-3)
    # a settled soft cube is close to a rigid motion of its rest shape: LBS reproduces it
    rest = scene._objects["soft"].spec.gaussians.means.astype(np.float64)
    expected = transform_points(scene.object_pose("soft"), rest)
    assert np.abs(means - expected).max() < 2e-3


def test_gripper_latches_on_finger_forces_and_lifts_by_friction():
    """Scene wiring of the latch: the fingers' mesh contact forces reach the controller, which stops
    closing at the default threshold; the cube then rises with the hand (no pinning)."""
    robot = load_builtin_arm("gripper")
    g = (np.arange(4) - 1.5) * 0.01
    pts = np.stack(np.meshgrid(g, g, g + 0.015, indexing="ij"), -1).reshape(-1, 3)
    cloud = surface_discs(pts.astype(np.float32), np.tile([0.0, 0.0, 1.0], (64, 1)), (0.8, 0.2, 0.2), 0.004)
    sim = SimParams(dt=1 / 30 / 200, substeps=200, ground_restitution=0.0, ground_friction=0.5,
                    object_collision=False, mesh_margin=0.004)
    cube = ObjectSpec("cube", pts, cloud, rigid=False, spring_radius=0.018)
    scene = Scene(robot, sample_robot_scan(robot, spacing=0.02), cloud.subset(slice(0, 1)), [cube],
                  [front_camera()], sim=sim)
    down = np.array([0.0, 1.0, 0.0, 0.0])
    q0 = robot.set_gripper(solve_ik(robot, ee_pose(np.array([0.4, 0.0, 0.02]), down), robot.home_q).q, 0.0)
    scene.reset(q0, {"cube": planar_pose(0.4, 0.0, 0.0)})
    threshold = scene.controller.config.grasp_force_threshold
    for _ in range(25):  # close on the cube
        scene.step(np.array([0.4, 0.0, 0.02, *down, 1.0]))
    assert scene.controller.latched and min(scene.finger_forces) > threshold
    held = scene.controller.gripper
    assert 0.0 < held < 1.0  # stopped closing before the fingers met
    for k in range(30):  # lift 6 cm with the gripper still commanded closed
        scene.step(np.array([0.4, 0.0, 0.02 + 0.002 * (k + 1), *down, 1.0]))
    rise = scene.controller.ee_pose()[2, 3] - 0.02
    assert scene.controller.gripper == held and scene.controller.latched
    assert rise > 0.05 and scene.particles("cube")[:, 2].min() > rise - 0.01
