"""Toy packing on the built-in `fast` cell: the toy and box, the inside rule on constructed states,
gymnasium conformance, determinism, the expert."""

import numpy as np
import pytest
from episode_helpers import assert_seeded_episode_repeats, expert_episode, place
from gymnasium.utils.env_checker import check_env

from twinbench.env import TwinEnv
from twinbench.tasks.gripper_expert import grasp_quat
from twinbench.tasks.toy_packing import make_expert
from twinbench.transforms import transform_points


@pytest.fixture(scope="module")
def env():
    return TwinEnv("toy-packing", preset="fast", success_rule="early")


def test_toy_has_softer_limbs_and_the_grid_pairs_toy_and_box_offsets(env):
    spec = env.twin.spec.object("toy")
    y = np.asarray(spec.spring_Y)
    assert y.shape == (len(spec.springs),) and y.min() < y.max()  # limbs softer than the torso
    states = env.rules.initial_states
    assert len(states) == 20 and set(states.grid) == {"toy", "box"}
    _, info = env.reset(seed=0, options={"init_state": 19})
    box = info["privileged"]["object_poses"]["box"]
    rest = env.twin.spec.colliders[0].pose
    np.testing.assert_allclose(box[:2, 3] - rest[:2, 3], states.grid["box"][19][:2], atol=1e-12)



def test_success_rule_on_a_packed_toy_and_a_near_miss(env):
    env.reset(seed=0, options={"init_state": 0})
    twin, rules = env.twin, env.rules
    rest = twin.rest_particles("toy")
    box = twin.collider_pose(env.state, "box")
    # packed: limbs tucked (the toy squeezed to 60 % of its footprint) and set on the box floor
    packed = rest * [0.6, 0.5, 1.0]
    hit, m = place(env, transform_points(box, packed))
    assert hit and m["inside_fraction"] == 1.0
    # near miss: the same toy 10 cm up -- its top pokes out above the walls (scaled height 13.65 cm)
    lifted = transform_points(box, packed + [0, 0, 0.10])
    hit, m = place(env, lifted)
    assert not hit and 0.5 < m["inside_fraction"] < rules.settings.inside_fraction
    # the toy as it is (limbs spread) astride the box's +x wall: half of it outside
    hit, m = place(env, transform_points(box, rest + [0.10, 0, 0]))
    assert not hit and 0.2 < m["inside_fraction"] < 0.8


def test_conforms_to_gymnasium_and_is_deterministic(env):
    check_env(env, skip_render_check=True)
    actions = np.random.default_rng(1).uniform(env.action_space.low, env.action_space.high, (6, 8))
    actions[:, 3:7] = grasp_quat((0.0, 1.0))
    assert_seeded_episode_repeats(env, actions, 7, 1, "toy")



@pytest.mark.slow
def test_expert_packs_the_whole_grid_under_the_final_rule():
    """Every grid state, full-length episodes judged on their last 100 frames (the default rule);
    benchmarks/expert_grid.py prints the same per state."""
    final = TwinEnv("toy-packing", preset="fast")
    failed = [i for i in range(20) if not expert_episode(final, make_expert(final), i)]
    assert not failed, f"the expert fails grid states {failed}"
