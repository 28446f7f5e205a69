"""Push-T reads its geometry from the twin (the block's `outline`, the robot's `tool_radius`): a T 0.7x the
built-in one (the reference study's, preset fast) is scored with its own outline, and the scripted expert
pushes it home."""

import dataclasses
import types

import numpy as np
import pytest

from twinbench.env import TwinEnv
from twinbench.evaluation.rollout import policy_observation
from twinbench.robot.builtin import PUSHERS
from twinbench.tasks.push_t import PushTTask, make_expert
from twinbench.transforms import planar_pose
from twinbench.twin.cells import PushTCell, push_t_cell
from twinbench.twin.shapes import TBlockShape

SCALE = 0.7
STUDY_T = TBlockShape(*PushTCell.preset("fast").t_shape)
STUDY_PUSHER_RADIUS = PUSHERS["pusher20"][0]  # the study's 20 cm pusher


@pytest.fixture(scope="module")
def small_env():
    env = TwinEnv("push-t", preset="fast", block_scale=SCALE, success_rule="early")
    env.reset(seed=0, options={"init_state": 0})
    return env


def shifted_overlap(t: TBlockShape, dx: float) -> float:
    """The fraction of a T's area that the same T moved by dx along x (|dx| < stem width) covers."""
    bar, stem = t.bar_length * t.bar_width, t.stem_width * t.stem_length
    return ((t.bar_length - dx) * t.bar_width + (t.stem_width - dx) * t.stem_length) / (bar + stem)


def test_the_scaled_twin_carries_its_own_outline_and_the_pusher_radius(small_env):
    spec = small_env.twin.spec
    block = spec.object("tblock")
    np.testing.assert_allclose(block.outline.polygon, STUDY_T.scaled(SCALE).outline_xy(), atol=1e-15)
    assert block.outline.height == pytest.approx(0.03 * SCALE)
    assert block.outline.area == pytest.approx(SCALE**2 * STUDY_T.outline().area, rel=1e-12)
    # the particles fill that outline (the cell scales the T and its lattice)
    assert block.outline.contains(block.particles, tol=1e-6).all()
    assert len(block.particles) == len(push_t_cell("fast").object("tblock").particles)
    assert spec.robot.tool_radius == STUDY_PUSHER_RADIUS
    assert small_env.rules.outline is block.outline and small_env.rules.tool_radius == STUDY_PUSHER_RADIUS


def test_the_scaled_t_is_scored_with_its_own_outline(small_env):
    twin, state = small_env.twin, small_env.state
    rest = PushTCell.preset("fast").block_pose  # (0.43, 0, -90 deg): the T's x axis along world -y
    on_rest = PushTTask(goal_pose=rest)
    on_rest.setup(twin, state)
    on_rest.reset(twin, state, {"block": np.zeros(3)})  # the T resting exactly on its goal
    hit, metrics = on_rest.frame(twin, state)
    assert hit and metrics["coverage"] == 1.0 and metrics["msd"] < 1e-12
    np.testing.assert_allclose(twin.object_pose(state, "tblock"), planar_pose(*rest), atol=1e-6)

    # The goal 2 cm along the T's x axis: the block covers the part of the goal T that a 0.7x T moved by
    # 2 cm covers (0.588); the built-in T's outline would say 0.712.
    moved = PushTTask(goal_pose=(rest[0], rest[1] - 0.02, rest[2]))
    moved.setup(twin, state)
    moved.reset(twin, state, {"block": np.zeros(3)})
    _, metrics = moved.frame(twin, state)
    own, builtin = shifted_overlap(STUDY_T.scaled(SCALE), 0.02), shifted_overlap(STUDY_T, 0.02)
    assert own == pytest.approx(0.5879, abs=1e-4) and builtin == pytest.approx(0.7115, abs=1e-4)
    assert metrics["coverage"] == pytest.approx(own, abs=0.02)
    assert metrics["msd"] == pytest.approx(0.02**2, rel=1e-4)  # every particle 2 cm from its goal


def test_the_goal_overlay_is_the_scaled_outline(small_env, fast_env):
    small, full = small_env.rules._overlay.sum(), fast_env.rules._overlay.sum()
    assert small / full == pytest.approx(SCALE**2, abs=0.04)


def test_a_twin_without_an_outline_or_tool_radius_is_refused():
    spec = push_t_cell("fast")
    no_outline = dataclasses.replace(spec, objects=(dataclasses.replace(spec.objects[0], outline=None),))
    fake_twin = types.SimpleNamespace(spec=no_outline, object_names=["tblock"], collider_names=[])
    with pytest.raises(ValueError, match=r"needs the outline of object 'tblock'.*twin.json"):
        PushTTask().setup(fake_twin, None)
    no_radius = dataclasses.replace(spec, robot=dataclasses.replace(spec.robot, urdf="my_arm.urdf",
                                                                    tool_radius=None))
    fake_twin.spec = no_radius
    with pytest.raises(ValueError, match=r"needs the radius of the pusher tip.*robot.tool_radius"):
        PushTTask().setup(fake_twin, None)


def test_the_expert_pushes_the_scaled_t_home(small_env):
    expert = make_expert(small_env)
    assert expert.outline is small_env.rules.outline and expert.pusher_radius == STUDY_PUSHER_RADIUS
    obs, info = small_env.reset(seed=0, options={"init_state": 3})
    expert.reset()
    steps, term, trunc = 0, False, False
    while not (term or trunc):
        action = expert.select_action(policy_observation(expert, obs, info))
        obs, _, term, trunc, info = small_env.step(action)
        steps += 1
    assert info["is_success"] and term, f"not home after {steps} steps: {info}"


def test_an_arm_that_cannot_reach_the_start_pose_is_named_with_how_far_it_stays(tmp_path):
    from twinbench.robot.model import load_robot

    # a 30 cm prismatic slide along z: the start (0.3, -0.2, 0.005), tool pointing down, is out of reach
    (tmp_path / "slide.urdf").write_text(
        '<robot name="slide"><link name="base"/><link name="tip"/><joint name="z" type="prismatic">'
        '<parent link="base"/><child link="tip"/><axis xyz="0 0 1"/>'
        '<limit lower="0" upper="0.3" effort="1" velocity="1"/></joint></robot>')
    twin = types.SimpleNamespace(robot=load_robot(tmp_path / "slide.urdf", load_meshes=False))
    task = PushTTask()
    far = (r"push-t: the task's start pose \(end effector 'tip' at \(0.3, -0.2, 0.005\) m .* orientation "
           r"wxyz \(0.0, 1.0, 0.0, 0.0\), any turn about the vertical\) is not reachable by slide "
           r"\(the closest configuration found is 360.6 mm and 180.0 deg away\)")
    with pytest.raises(ValueError, match=far):
        task.start_configuration(twin, (0.3, -0.2, 0.005), (0.0, 1.0, 0.0, 0.0))
