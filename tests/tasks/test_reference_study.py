"""The built-in cells and tasks against the reference study's numbers (kywind/real2sim-eval: cfg/gs/*.yaml,
cfg/env/xarm_*.yaml, experiments/utils/calculate_success_*.py, experiments/eval_policy.py, T_final_state.pkl;
shuosha/policy_training configs/inference/*.json), written out here as the study lists them."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.tasks.base import InitialStates, SuccessWindow
from twinbench.tasks.push_t import PushTTask
from twinbench.tasks.rope_routing import RopeRoutingTask
from twinbench.tasks.toy_packing import ToyPackingTask
from twinbench.transforms import planar_pose
from twinbench.twin.cells import push_t_cell


def study_grid(xy, theta, one_to_one):
    """The study's gs_renderer index rule: xy[i // len(theta)], theta[i % len(theta)] (or paired)."""
    if one_to_one:
        return [(x, y, np.deg2rad(t)) for (x, y), t in zip(xy, theta, strict=True)]
    return [(*xy[i // len(theta)], np.deg2rad(theta[i % len(theta)])) for i in range(len(xy) * len(theta))]


def same_states(ours, theirs):
    ours, theirs = np.asarray(ours), np.asarray(theirs)
    assert ours.shape == theirs.shape
    np.testing.assert_allclose(ours[:, :2], theirs[:, :2], atol=1e-12)
    dth = np.angle(np.exp(1j * (ours[:, 2] - theirs[:, 2])))  # the same rotation
    np.testing.assert_allclose(dth, 0.0, atol=1e-12)


def test_push_t_grid_is_the_studys_list_index_by_index():
    xy = [(-0.05, -0.05), (-0.05, 0.05), (0.05, -0.05), (0.05, 0.05)]
    theirs = study_grid(xy, [45, 135, 225, 315], False)
    same_states(PushTTask().initial_states.grid["block"], theirs)
    assert np.rad2deg(PushTTask().initial_states.grid["block"][2, 2]) == pytest.approx(225.0)


def test_rope_grid_is_the_studys_list_index_by_index():
    xy = [(x, y) for x in (-0.05, 0.0, 0.05) for y in (-0.05, 0.0, 0.05)]
    same_states(RopeRoutingTask().initial_states.grid["rope"], study_grid(xy, [-10, 0, 10], False))


def test_toy_grid_is_the_studys_list_with_the_toy_fastest():
    toy = study_grid([(0, 0), (-0.05, 0), (0.05, 0), (0, -0.05), (0, 0.03)], [0, -5, 5, -5, 5], True)
    box = study_grid([(0, 0), (-0.05, 0), (0.05, 0), (0, 0.05)], [0, -5, 5, 5], True)
    grid = ToyPackingTask().initial_states.grid
    assert len(grid["toy"]) == 20
    for i in range(20):  # the study: object index i % 5, box index i // 5
        same_states(grid["toy"][i : i + 1], [toy[i % 5]])
        same_states(grid["box"][i : i + 1], [box[i // 5]])


def test_product_orders():
    a, b = np.arange(6.0).reshape(2, 3), 10 + np.arange(9.0).reshape(3, 3)
    lo = {"a": (0, 0, 0), "b": (0, 0, 0)}
    slow = InitialStates.product({"a": a, "b": b}, lo, lo)
    fast = InitialStates.product({"a": a, "b": b}, lo, lo, fastest="first")
    assert [r[0] for r in slow.grid["a"]] == [0, 0, 0, 3, 3, 3]
    assert [r[0] for r in fast.grid["a"]] == [0, 3, 0, 3, 0, 3]
    assert [r[0] for r in fast.grid["b"]] == [10, 10, 13, 13, 16, 16]
    with pytest.raises(ValueError, match="fastest"):
        InitialStates.product({"a": a}, {"a": lo["a"]}, {"a": lo["a"]}, fastest="middle")


def test_window_is_at_least_30_of_the_last_100_and_settling_is_30():
    win = SuccessWindow(100, 30)
    for k in range(100):
        win.update(k < 30)
    assert win.success  # exactly 30 hits: the study's `count >= 30`
    win.update(False)  # the oldest hit leaves the window
    assert not win.success
    for cls in (PushTTask, RopeRoutingTask, ToyPackingTask):
        s = cls().settings
        assert (s.success_window, s.success_min_hits, s.settle_steps) == (100, 30, 30)


def test_push_t_reference_cell_matches_the_study():
    spec = push_t_cell("fast")
    block = spec.object("tblock")
    ext = block.particles.max(0) - block.particles.min(0)
    np.testing.assert_allclose(ext, [0.15, 0.15, 0.03], atol=1e-6)  # T_final_state.pkl: 15.0 x 15.0 x 3 cm
    assert block.outline.area == pytest.approx(0.15 * 0.04 + 0.11 * 0.04)
    np.testing.assert_allclose(block.rest_pose, planar_pose(0.43, 0.0, -np.pi / 2), atol=1e-12)  # T.yaml
    goal = block.goal_pose
    np.testing.assert_allclose(goal[:2, 3], [0.4193, 0.0015], atol=1e-4)
    stem = goal[:3, :3] @ [0.0, -1.0, 0.0]  # the stem points along the T frame's -y
    assert stem[0] < -0.99  # toward the robot
    assert PushTTask().settings.pusher_start == (0.30, -0.20)  # cfg/env/xarm_pusher.yaml init_eef_xyz
    front = next(c for c in spec.cameras if c.name == "front")
    assert front.sensor_size == (848, 480) and front.output_hw == (240, 240)
    assert front.crop == (184, 100, 440, 280)  # pusht.json fixed_pre_crop [100, 380, 184, 624]
    np.testing.assert_allclose(front.pose[:3, 3], [0.88302639, 0.05390846, 0.39760339], atol=1e-8)
    assert front.intrinsics[0] == pytest.approx(427.2920227050781)
    wrist = next(c for c in spec.cameras if c.name == "wrist")
    assert wrist.crop == (184, 0, 480, 480) and wrist.mount_link == "link7"  # link_eef = link7 (offset 0)
    np.testing.assert_allclose(wrist.pose[:3, 3], [0.070151686668396, -0.006011864222586155, 0.03072427])


def test_push_t_goal_fits_the_studys_final_state():
    """The goal outline at the goal pose covers the study's final-state T (the particles' bounds, measured
    from T_final_state.pkl: x 0.3208-0.4712, y -0.0730-0.0771) within 3 mm."""
    spec = push_t_cell("fast")
    block = spec.object("tblock")
    poly = block.outline.polygon
    world = poly @ block.goal_pose[:2, :2].T + block.goal_pose[:2, 3]
    np.testing.assert_allclose(world.min(0), [0.3208, -0.0730], atol=3e-3)
    np.testing.assert_allclose(world.max(0), [0.4712, 0.0771], atol=3e-3)


def test_small_presets_keep_the_earlier_cell():
    small = push_t_cell("small-fast").object("tblock")
    ext = small.particles.max(0) - small.particles.min(0)
    np.testing.assert_allclose(ext, [0.12, 0.12, 0.03], atol=1e-6)
    assert small.goal_pose is None
    np.testing.assert_allclose(small.rest_pose, planar_pose(0.5, 0.0, 0.0))


def test_rope_and_toy_cells_use_the_studys_cameras_and_crops():
    from twinbench.twin.cells import rope_routing_cell, toy_packing_cell

    for spec, crop, hw in [
        (rope_routing_cell("fast"), (0, 0, 848, 480), (120, 212)),  # rope policy: full frame -> 120 x 212
        (toy_packing_cell("fast"), (100, 0, 648, 480), (240, 240)),  # sloth policy: cols 100-748 -> 240 x 240
    ]:
        front, wrist = (next(c for c in spec.cameras if c.name == n) for n in ("front", "wrist"))
        assert front.sensor_size == (848, 480) and front.crop == crop and front.output_hw == hw
        np.testing.assert_allclose(front.pose[:3, 3], [0.88302639, 0.05390846, 0.39760339], atol=1e-8)
        assert wrist.mount_link == "link7" and wrist.output_hw == hw
        np.testing.assert_allclose(wrist.pose[:3, 3], [0.070151686668396, -0.006011864222586155, 0.03072427])
    for spec in (rope_routing_cell("small-fast"), toy_packing_cell("small-fast")):  # the earlier cells
        assert all(c.crop is None and c.output_hw == (240, 240) for c in spec.cameras)


def test_push_t_pusher_is_the_studys():
    """xarm7_with_pusher.urdf: pusher_base_link 15 mm below link_eef, pusher_20cm.stl a 200 mm rod of radius
    ~10.2 mm; cfg/env/xarm_pusher.yaml: the flange at z = 0.22, so the tip 5 mm above the table."""
    from twinbench.tasks.base import tool_offset
    from twinbench.twin.build import load_spec_robot

    spec = push_t_cell("fast")
    assert spec.robot.urdf == "builtin:xarm7_pusher20" and spec.robot.tool_radius == pytest.approx(0.0102)
    robot = load_spec_robot(spec.robot)
    q = robot.home_q
    tip = np.linalg.inv(robot.link_pose(q, "link7")) @ robot.ee_pose(q)
    np.testing.assert_allclose(tip[:3, 3], [0.0, 0.0, 0.215], atol=1e-12)  # the ee is the tip
    assert tool_offset(robot) == pytest.approx([0.0, 0.0, 0.0])
    assert spec.controller.planar_height + 0.215 == pytest.approx(0.22)
    assert push_t_cell("small-fast").robot.tool_radius == 0.015  # the earlier cell keeps its 15 mm rod


def test_gripper_cells_act_on_the_flange_as_the_study():
    """The study's state and actions are the flange (`link_eef` = link7) pose; the small cells keep the tool
    point (`tcp`, 13 cm below it), as do twins that name no end-effector (twin.json v1/v2)."""
    from twinbench.tasks.base import tool_offset
    from twinbench.tasks.gripper_expert import GripperExpert, Leg
    from twinbench.twin.build import load_spec_robot
    from twinbench.twin.cells import RopeCell, ToyCell, gripper_robot
    from twinbench.twin.spec import RobotSpec

    for cell in (RopeCell, ToyCell):
        assert [cell.preset(p).ee_frame for p in ("reference", "fast", "small", "small-fast")] == [
            "flange", "flange", "tool", "tool"]
    robot = load_spec_robot(gripper_robot(ee_frame="flange"))
    assert robot.ee_link == "link7"
    np.testing.assert_allclose(tool_offset(robot), [0.0, 0.0, 0.13], atol=1e-12)
    old = load_spec_robot(RobotSpec("builtin:xarm7_gripper"))
    assert old.ee_link == "tcp" and tool_offset(old) == pytest.approx([0.0, 0.0, 0.0])

    class OneLeg(GripperExpert):  # the tool point 5 cm above (0.5, 0.1), pointing down
        def plan(self, s):
            return [Leg("hold", np.array([0.5, 0.1, 0.05]), np.array([0.0, 1.0, 0.0, 0.0]), 0.0)]

    obs = {"environment_state": np.zeros(1), "agent_pos": np.r_[0.4, 0.0, 0.3, 0.0, 1.0, 0.0, 0.0, 0.0]}
    np.testing.assert_allclose(OneLeg(0.01, (0.0, 0.0, 0.13)).select_action(obs)[:3], [0.5, 0.1, 0.18],
                               atol=1e-6)  # the flange 13 cm above the tool point
    np.testing.assert_allclose(OneLeg(0.01).select_action(obs)[:3], [0.5, 0.1, 0.05], atol=1e-6)


def study_rope_crossings(x, springs, center=(0.62, 0.05, 0.0)):
    """calculate_success_rope.py as the study writes it: every spring segment, the planes y = y_min and
    y = y_max of the world-aligned box center +- (1.75, 1.75) cm in x, y and z in [0, 3] cm, hits within
    the box's x-z rectangle (segments in the plane counted when an end lies in the rectangle)."""
    lo = np.array(center) - [0.0175, 0.0175, 0.0]
    hi = np.array(center) + [0.0175, 0.0175, 0.03]
    p0, p1 = x[springs[:, 0]], x[springs[:, 1]]
    out = []
    for y in (lo[1], hi[1]):
        dy = p1[:, 1] - p0[:, 1]
        par = np.isclose(dy, 0.0, atol=1e-12)
        t = np.where(par, 0.0, (y - p0[:, 1]) / np.where(par, 1.0, dy))
        pt = p0 + t[:, None] * (p1 - p0)
        rect = (pt[:, 0] >= lo[0]) & (pt[:, 0] <= hi[0]) & (pt[:, 2] >= lo[2]) & (pt[:, 2] <= hi[2])
        out.append(int(np.sum(~par & (t >= 0) & (t <= 1) & rect)))
    return out


def test_rope_cell_clip_box_and_rule_match_the_study():
    """cfg/gs/rope.yaml: the clip at (0.62, 0.05) turned -2 deg, the rope at (0.36, 0); the success box of
    calculate_success_rope.py and its 100 springs per opening, on the rope laid through the box."""
    from twinbench.physics.model import radius_springs
    from twinbench.tasks.rope_routing import count_crossings
    from twinbench.transforms import invert_pose, transform_points
    from twinbench.twin.cells import rope_routing_cell

    for preset in ("reference", "fast"):
        spec = rope_routing_cell(preset)
        clip = spec.colliders[0]
        np.testing.assert_allclose(clip.pose, planar_pose(0.62, 0.05, 0.0), atol=1e-12)  # the box's frame
        assert clip.channel == (0.035, 0.03, 0.035)
        v = clip.vertices  # the walls: parallel to the channel axis turned by -2 deg
        wall = v[v[:, 0] > 0.02]
        edge = wall[np.argsort(wall[:, 1])][[0, -1]]
        assert np.rad2deg(np.arctan2(*(edge[1] - edge[0])[[0, 1]])) == pytest.approx(2.0, abs=0.3)
        rope = spec.objects[0]
        np.testing.assert_allclose(rope.rest_pose[:2, 3], [0.36, 0.0])
        assert spec.robot.ee_link == "link7" and front_crop(spec) == (0, 0, 848, 480)
        # the rope laid along y through the box's centre on the table
        springs = radius_springs(rope.particles, rope.spring_radius, rope.max_neighbors)
        laid = transform_points(planar_pose(0.62, 0.05, np.pi / 2), rope.particles)
        theirs = study_rope_crossings(laid, springs)
        local = transform_points(invert_pose(clip.pose), laid)
        ours = [count_crossings(local, springs, y, 0.0175, 0.03) for y in (-0.0175, 0.0175)]
        assert ours == theirs and min(theirs) == {"reference": 204, "fast": 180}[preset]  # the whole section
        # 1.5 cm to the side: only part of the section lies in the openings
        side = study_rope_crossings(laid + [0.0215, 0.0, 0.0], springs)
        assert 0 < max(side) < 100
    assert RopeRoutingTask().settings.crossing_threshold == 100


def front_crop(spec):
    return next(c for c in spec.cameras if c.name == "front").crop


def test_toy_cell_matches_the_studys_sizes():
    """cfg/gs/sloth.yaml: the sloth at (0.5, -0.17), the box at (0.45, 0.18); calculate_success_sloth.py:
    3,095 particles, the box's bounding box 0.2 x 0.13 x 0.27 m (its volume checked to 1e-6 m^3), 3,050
    inside."""
    from twinbench.twin.cells import toy_packing_cell

    spec = toy_packing_cell("reference")
    toy, box = spec.objects[0], spec.colliders[0]
    assert len(toy.particles) == 3095
    ext = np.ptp(toy.particles, 0)
    assert 0.09 < ext[0] < 0.11 and 0.15 < ext[1] < 0.17 and 0.04 < ext[2] < 0.06
    box_ext = np.ptp(box.vertices, 0)
    np.testing.assert_allclose(sorted(box_ext), sorted([0.2, 0.13, 0.27]), atol=1e-9)
    assert abs(np.prod(box_ext) - 0.2 * 0.13 * 0.27) < 1e-6
    np.testing.assert_allclose(toy.rest_pose[:2, 3], [0.5, -0.17])
    np.testing.assert_allclose(box.pose[:2, 3], [0.45, 0.18])
    assert ToyPackingTask().settings.inside_fraction * 3095 == pytest.approx(3050)
    assert len(toy_packing_cell("fast").objects[0].particles) < 3095  # the fast lattice is coarser
    assert spec.robot.ee_link == "link7" and front_crop(spec) == (100, 0, 648, 480)
