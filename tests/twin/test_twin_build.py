"""build_twin: Gaussians follow the robot (FK) and the objects (rigid fit / LBS); friction grasp + latch."""

import numpy as np
import pytest

from twinbench.gaussians.primitives import surface_discs
from twinbench.physics import SimParams
from twinbench.robot.controller import ControllerConfig
from twinbench.robot.ik import solve_ik
from twinbench.transforms import planar_pose, transform_points
from twinbench.transforms import pose_matrix as ee_pose
from twinbench.twin import ObjectSpec, RobotSpec, TwinSpec, build_twin
from twinbench.twin.cells import front_camera

N_OBJ_GAUSSIANS = 200
DOWN = np.array([0.0, 1.0, 0.0, 0.0])


def _cube_points() -> np.ndarray:
    g = (np.arange(4) - 1.5) * 0.01
    return np.stack(np.meshgrid(g, g, g + 0.015, indexing="ij"), -1).reshape(-1, 3)


def _object(name: str, binding: str, spring_y: float) -> ObjectSpec:
    pts = _cube_points()
    rng = np.random.default_rng(0)
    means = rng.uniform(pts.min(0), pts.max(0), (N_OBJ_GAUSSIANS, 3)).astype(np.float32)
    cloud = surface_discs(means, np.tile([0.0, 0.0, 1.0], (N_OBJ_GAUSSIANS, 1)), (0.8, 0.2, 0.2), 0.004)
    return ObjectSpec(
        name, pts, gaussians=cloud, binding=binding, spring_radius=0.018, spring_Y=spring_y, max_neighbors=50
    )


def _disc():
    return surface_discs(np.zeros((1, 3), np.float32), np.array([[0.0, 0, 1]]), (0.5, 0.5, 0.5), 0.01)


@pytest.fixture(scope="module")
def setup():
    sim = SimParams(
        dt=1 / 30 / 300,
        substeps=300,
        ground_restitution=0.0,
        ground_friction=0.5,
        object_collision=False,
        mesh_margin=0.006,
    )
    spec = TwinSpec(
        "two-cubes",
        RobotSpec("builtin:xarm7_pusher", scan_spacing=0.02),
        objects=(_object("block", "rigid", 3e4), _object("soft", "lbs", 3e3)),
        cameras=(front_camera(),),
        background=_disc(),
        sim=sim,
        controller=ControllerConfig(action_mode="planar", planar_height=0.01),
    )
    return build_twin(spec)


def _segments(twin, state) -> dict[str, np.ndarray]:
    means = twin.pose_gaussians(state).means.numpy()
    a = 1 + len(twin.robot_gaussians)
    return {
        "robot": means[1:a],
        "block": means[a : a + N_OBJ_GAUSSIANS],
        "soft": means[a + N_OBJ_GAUSSIANS :],
    }


def test_reset_places_robot_and_object_gaussians(setup):
    twin, state = setup
    poses = {"block": planar_pose(0.5, 0.1, 0.3), "soft": planar_pose(0.5, -0.1, -0.2)}
    twin.reset(state, None, poses)
    seg = _segments(twin, state)
    # device path (state buffer) == host path (RobotGaussians.posed) at the same configuration
    np.testing.assert_allclose(seg["robot"], twin.robot_gaussians.posed(state.robot.q).means, atol=1e-5)
    for name in ("block", "soft"):
        rest = twin.spec.object(name).gaussians.means.astype(np.float64)
        np.testing.assert_allclose(seg[name], transform_points(poses[name], rest), atol=1e-5)
        np.testing.assert_allclose(twin.object_pose(state, name), poses[name], atol=1e-6)
    with pytest.raises(ValueError, match="unknown objects"):
        twin.reset(state, None, {"ball": np.eye(4)})
    twin.reset(state)  # default: the objects' rest poses (identity here)
    np.testing.assert_allclose(twin.particles(state, "block"), _cube_points(), atol=1e-7)


def test_pushed_block_carries_its_gaussians_rigidly(setup):
    twin, state = setup
    tip_down = ee_pose(np.array([0.35, 0.0, 0.01]), DOWN)  # pusher at table height
    q0 = solve_ik(twin.robot, tip_down, twin.robot.home_q).q
    twin.reset(state, q0, {"block": planar_pose(0.45, 0.0, 0.0), "soft": planar_pose(0.3, -0.2, 0.0)})
    start = twin.ee_state(state)
    for k in range(45):  # sweep the pusher through the block's position along +x
        twin.step(state, np.array([start[0] + 0.006 * (k + 1), 0.0]))
    pose = twin.object_pose(state, "block")
    assert pose[0, 3] > 0.46  # pushed along +x
    seg = _segments(twin, state)
    rest = twin.spec.object("block").gaussians.means.astype(np.float64)
    np.testing.assert_allclose(seg["block"], transform_points(pose, rest), atol=1e-5)
    np.testing.assert_allclose(seg["robot"], twin.robot_gaussians.posed(state.robot.q).means, atol=1e-5)


def test_soft_object_gaussians_follow_its_particles(setup):
    twin, state = setup
    drop = planar_pose(0.3, -0.2, 0.4)
    drop[2, 3] = 0.03  # released 3 cm above the table: it falls, lands and squashes a little
    twin.reset(state, None, {"soft": drop, "block": planar_pose(0.6, 0.2, 0.0)})
    for _ in range(12):
        twin.step(state, twin.ee_state(state))
    particles = twin.particles(state, "soft")
    assert particles[:, 2].min() < 1e-3  # on the table
    means = _segments(twin, state)["soft"]
    lo, hi = particles.min(0), particles.max(0)
    assert np.all(means >= lo - 2e-3) and np.all(means <= hi + 2e-3)
    # a settled soft cube is close to a rigid motion of its rest shape: LBS reproduces it
    rest = twin.spec.object("soft").gaussians.means.astype(np.float64)
    expected = transform_points(twin.object_pose(state, "soft"), rest)
    assert np.abs(means - expected).max() < 2e-3


def test_two_states_of_one_twin_are_independent(setup):
    twin, state = setup
    other = twin.new_state()
    twin.reset(state, None, {"soft": planar_pose(0.3, -0.2, 0.0), "block": planar_pose(0.6, 0.2, 0.0)})
    lifted = planar_pose(0.3, -0.2, 0.0)
    lifted[2, 3] = 0.05
    twin.reset(other, None, {"soft": lifted, "block": planar_pose(0.6, 0.2, 0.0)})
    twin.step(other, twin.ee_state(other))
    # the first state did not move; the other one fell
    np.testing.assert_allclose(twin.particles(state, "soft")[:, 2].min(), 0.0, atol=1e-6)
    assert twin.particles(other, "soft")[:, 2].min() > 0.04  # fell less than 1 cm in one frame


def test_num_worlds_gives_one_state_per_world_and_bad_counts_are_refused(setup):
    twin, _ = setup
    many, states = build_twin(twin.spec, num_worlds=3)
    assert [s.world for s in states] == [0, 1, 2] and many.num_worlds == 3
    with pytest.raises(ValueError, match="step_worlds"):
        many.step(states[0], np.zeros(2))
    with pytest.raises(ValueError, match="in order"):
        many.step_worlds(states[::-1], [None] * 3)
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="num_worlds"):
            build_twin(twin.spec, num_worlds=bad)


def test_render_worlds_renders_every_world_in_one_call_as_each_alone(setup):
    """Worlds at different poses: one batched render gives each world's own images, equal to rendering
    that world by itself, and the worlds' images differ."""
    twin, _ = setup
    many, states = build_twin(twin.spec, num_worlds=3)
    def poses(k):
        return {"block": planar_pose(0.45, -0.1 + 0.1 * k, 0.3 * k), "soft": planar_pose(0.3, 0.2, 0.5 * k)}

    for k, state in enumerate(states):
        many.reset(state, None, poses(k))
    together = many.render_worlds(states)
    assert len(together) == 3 and all(set(d) == set(many.cameras) for d in together)
    for state, images in zip(states, together, strict=True):
        for name, out in many.render(state).items():
            np.testing.assert_array_equal(images[name].rgb, out.rgb)
            np.testing.assert_array_equal(images[name].depth, out.depth)
    name = next(iter(many.cameras))
    assert not np.array_equal(together[0][name].rgb, together[2][name].rgb)
    assert many.render_worlds([]) == []
    # the posers run once for all worlds (rigid, LBS and robot Gaussians in one buffer): a world's Gaussians
    # and images equal a one-world twin's in the same state, also after the soft body moved
    many.step_worlds(states, [None] * 3)
    one, alone = build_twin(twin.spec)
    one.reset(alone, None, poses(1))
    one.step(alone, None)
    posed = many.pose_worlds(states)[1]
    ref = one.pose_gaussians(alone)
    for field in ("means", "quats", "sh"):
        np.testing.assert_array_equal(getattr(posed, field).numpy(), getattr(ref, field).numpy())
    for name, out in one.render(alone).items():
        np.testing.assert_array_equal(many.render_worlds(states)[1][name].rgb, out.rgb)


def test_gripper_latches_on_finger_forces_and_lifts_by_friction():
    """The fingers' mesh contact forces reach the controller, which stops closing at the default
    threshold; the cube then rises with the hand (no pinning)."""
    pts = _cube_points()
    cloud = surface_discs(pts.astype(np.float32), np.tile([0.0, 0.0, 1.0], (64, 1)), (0.8, 0.2, 0.2), 0.004)
    sim = SimParams(
        dt=1 / 30 / 200,
        substeps=200,
        ground_restitution=0.0,
        ground_friction=0.5,
        object_collision=False,
        mesh_margin=0.004,
    )
    cube = ObjectSpec("cube", pts, gaussians=cloud, binding="lbs", spring_radius=0.018, max_neighbors=50)
    twin, state = build_twin(
        TwinSpec(
            "grasp",
            RobotSpec("builtin:xarm7_gripper", scan_spacing=0.02),
            objects=(cube,),
            cameras=(front_camera(),),
            sim=sim,
        )
    )
    robot = twin.robot
    q0 = robot.set_gripper(solve_ik(robot, ee_pose(np.array([0.4, 0.0, 0.02]), DOWN), robot.home_q).q, 0.0)
    twin.reset(state, q0, {"cube": planar_pose(0.4, 0.0, 0.0)})
    threshold = twin.controller.config.grasp_force_threshold
    for _ in range(25):  # close on the cube
        twin.step(state, np.array([0.4, 0.0, 0.02, *DOWN, 1.0]))
    assert state.robot.latched and min(state.finger_forces) > threshold
    held = state.robot.gripper
    assert 0.0 < held < 1.0  # stopped closing before the fingers met
    for k in range(30):  # lift 6 cm with the gripper still commanded closed
        twin.step(state, np.array([0.4, 0.0, 0.02 + 0.002 * (k + 1), *DOWN, 1.0]))
    rise = robot.ee_pose(state.robot.q)[2, 3] - 0.02
    assert state.robot.gripper == held and state.robot.latched
    assert rise > 0.05 and twin.particles(state, "cube")[:, 2].min() > rise - 0.01


def test_colliders_are_placed_per_episode_with_their_gaussians():
    """A box collider moved at reset: a cube dropped above its new place lands on it (not on the table),
    and the box's Gaussians are posed there too."""
    import trimesh

    from twinbench.twin import ColliderSpec

    box = trimesh.creation.box(extents=(0.1, 0.1, 0.04), transform=np.diag([1.0, 1, 1, 1]))
    box.vertices[:, 2] += 0.02  # box frame: bottom face on z = 0
    top = surface_discs(
        np.array([[0.0, 0.0, 0.04]], np.float32), np.array([[0.0, 0, 1]]), (0.2, 0.8, 0.2), 0.01
    )
    sim = SimParams(
        dt=1 / 30 / 200, substeps=200, ground_restitution=0.0, object_collision=False, mesh_margin=0.004
    )
    cube = ObjectSpec("cube", _cube_points(), spring_radius=0.018, max_neighbors=50)
    spec = TwinSpec(
        "box",
        RobotSpec("builtin:xarm7_pusher", scan_spacing=0.05),
        objects=(cube,),
        colliders=(ColliderSpec("box", box.vertices, box.faces, planar_pose(0.5, 0.3, 0.0), gaussians=top),),
        cameras=(front_camera(),),
        sim=sim,
        controller=ControllerConfig(action_mode="planar", planar_height=0.2),
    )
    twin, state = build_twin(spec)
    moved = planar_pose(0.45, -0.2, 0.5)
    above = planar_pose(0.45, -0.2, 0.0)
    above[2, 3] = 0.06
    twin.reset(state, None, {"box": moved, "cube": above})
    for _ in range(20):
        twin.step(state, twin.ee_state(state))
    z = twin.particles(state, "cube")[:, 2]
    assert abs(z.min() - 0.04) < 0.006  # resting on the box top (4 cm), not on the table
    np.testing.assert_allclose(twin.collider_pose(state, "box"), moved)
    g = twin.pose_gaussians(state).means.numpy()[-1]
    np.testing.assert_allclose(g, [0.45, -0.2, 0.04], atol=1e-6)
    twin.reset(state)  # back to the spec's pose: the cube's rest pose is the origin, the box at (0.5, 0.3)
    np.testing.assert_allclose(twin.pose_gaussians(state).means.numpy()[-1], [0.5, 0.3, 0.04], atol=1e-6)
    with pytest.raises(ValueError, match="unique"):
        TwinSpec(
            "dup",
            spec.robot,
            objects=(cube,),
            colliders=(ColliderSpec("cube", box.vertices, box.faces),),
            cameras=spec.cameras,
        )


def test_fixed_link_gaussians_are_stored_posed_and_rendered_as_static(setup):
    """The robot's Gaussians on links no joint moves (the base) are posed once, at build: they sit in the
    buffer as posing would put them at any q, the poser leaves them alone, and renders count them with the
    static scene (the render cache keeps them; cached renders still equal full ones)."""
    twin, state = setup
    rg = twin.robot_gaussians
    n_base = int(twin.robot.fixed_links[rg.link_index].sum())
    assert n_base == int((rg.link_index == 0).sum()) > 0
    assert twin._robot_range == (1 + n_base, len(rg) - n_base)  # after the one background Gaussian
    twin.reset(state, None, {"block": planar_pose(0.5, 0.1, 0.3), "soft": planar_pose(0.3, -0.2, 0.0)})
    start = twin.ee_state(state)
    cache = twin.render_cache
    for k in range(3):
        twin.step(state, np.array([start[0] + 0.02 * (k + 1), start[1]]))
        seg = _segments(twin, state)
        np.testing.assert_array_equal(seg["robot"], twin.robot_gaussians.posed(state.robot.q).means)
        cached = twin.render(state)
        twin.render_cache = None
        full = twin.render(state)
        twin.render_cache = cache
        for name in full:
            np.testing.assert_array_equal(cached[name].rgb, full[name].rgb)
    assert cache.hits >= 1


def test_a_heavy_contact_mesh_is_warned_about_and_the_builtin_pusher_is_not(tmp_path, recwarn):
    import trimesh

    from twinbench.robot.builtin import load_builtin_arm
    from twinbench.robot.model import load_robot
    from twinbench.twin.build import warn_heavy_contact_mesh

    trimesh.creation.icosphere(subdivisions=5, radius=0.02).export(tmp_path / "ball.stl")  # 20,480 faces
    (tmp_path / "arm.urdf").write_text(
        '<robot name="arm"><link name="base"/><link name="tip"><collision><geometry>'
        '<mesh filename="ball.stl"/></geometry></collision></link><joint name="z" type="prismatic">'
        '<parent link="base"/><child link="tip"/><axis xyz="0 0 1"/>'
        '<limit lower="0" upper="0.3" effort="1" velocity="1"/></joint></robot>')
    warn_heavy_contact_mesh(load_builtin_arm("pusher"), "pusher")
    assert not recwarn.list
    heavy = r"arm.urdf: contact link 'tip' has a collision mesh of 20,480 faces"
    with pytest.warns(UserWarning, match=heavy):
        warn_heavy_contact_mesh(load_robot(tmp_path / "arm.urdf", contact_links=("tip",)), "tip")
