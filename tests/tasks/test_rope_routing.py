"""Rope routing on the built-in `fast` cell: friction grasp and hang, the crossing rule on constructed
states, gymnasium conformance, determinism, the expert."""

import numpy as np
import pytest
from episode_helpers import assert_seeded_episode_repeats, expert_episode, place
from gymnasium.utils.env_checker import check_env

from twinbench.env import TwinEnv
from twinbench.tasks.gripper_expert import TCP_ABOVE_TIPS, grasp_quat
from twinbench.tasks.rope_routing import count_crossings, make_expert
from twinbench.transforms import planar_pose, transform_points


@pytest.fixture(scope="module")
def env():
    return TwinEnv("rope-routing", preset="fast", success_rule="early")


def test_counting_springs_across_a_plane():
    pts = np.array(
        [
            [0.0, -0.01, 0.01],
            [0.0, 0.01, 0.01],
            [0.05, -0.01, 0.01],
            [0.05, 0.01, 0.01],
            [0.0, -0.01, 0.05],
            [0.0, 0.01, 0.05],
        ]
    )
    springs = np.array([[0, 1], [2, 3], [4, 5], [0, 2]])
    # only the first crosses y = 0 within |x| <= 0.01, 0 <= z <= 0.03 (2: off in x, 3: too high, 4: parallel)
    assert count_crossings(pts, springs, 0.0, 0.01, 0.03) == 1
    assert count_crossings(pts, springs, 0.0, 0.1, 0.1) == 3


def test_gripper_lifts_the_rope_by_friction_it_hangs_and_drops_when_released(env):
    obs, info = env.reset(seed=0, options={"init_state": 13})
    twin, state = env.twin, env.state
    assert info["grasp"] == "open"
    rope = twin.particles(state, "rope")
    end = rope[np.argmax(rope[:, 0])]  # the rope lies along +x; grasp 1 cm in from its +x end
    quat = grasp_quat((1.0, 0.0))
    grasp = np.array([end[0] - 0.01, end[1], TCP_ABOVE_TIPS + 0.002])
    flange = env.rules.tool_offset  # actions and agent_pos are the flange's, 13 cm above the tool point
    assert flange == pytest.approx([0.0, 0.0, 0.13])

    def act(p, g):
        return np.r_[p + flange, quat, g].astype(np.float32)

    for _ in range(60):  # over the end, then down to it (the velocity-control mimic lags its targets)
        obs, *_, info = env.step(act(grasp + [0, 0, 0.06], 0.0))
    for _ in range(25):
        obs, *_, info = env.step(act(grasp, 0.0))
    assert np.linalg.norm(obs["agent_pos"][:3] - flange - grasp) < 0.006
    tool = info["privileged"]["tool_pose"][:3, 3]  # the tool point stays available
    np.testing.assert_allclose(tool, obs["agent_pos"][:3] - flange, atol=1e-5)
    for _ in range(25):
        obs, *_, info = env.step(act(grasp, 1.0))
    assert info["grasp"] == "holding"  # the thin rope never loads the fingers to the latch: a closed pinch
    for k in range(50):
        obs, *_, info = env.step(act(grasp + [0, 0, 0.004 * (k + 1)], 1.0))
    rope = twin.particles(state, "rope")
    held, free = rope[np.argmax(rope[:, 2])], rope[np.argmin(rope[:, 2])]
    assert held[2] > 0.15  # the grasped end rose with the hand (pure friction: no particle is attached)
    assert free[2] < held[2] - 0.1  # the rope hangs: its free end far below the grasped end
    assert info["grasp"] == "holding"
    for _ in range(25):
        obs, *_, info = env.step(act(grasp + [0, 0, 0.2], 0.0))
    assert twin.particles(state, "rope")[:, 2].max() < 0.03  # released: it fell back onto the table
    assert info["grasp"] == "open"


def test_closing_on_air_is_reported(env):
    obs, info = env.reset(seed=0, options={"init_state": 13})
    for _ in range(20):  # close high above the rope
        obs, *_, info = env.step(np.r_[0.35, 0.0, 0.33, grasp_quat((1.0, 0.0)), 1.0].astype(np.float32))
    assert info["grasp"] == "closed_on_air"



def test_success_rule_on_a_routed_rope_and_a_near_miss(env):
    env.reset(seed=0, options={"init_state": 13})
    twin, rules = env.twin, env.rules
    rest = twin.rest_particles("rope")
    clip = twin.collider_pose(env.state, "clip")
    # routed: the rope straight along the channel axis (clip y), centred in the clip, on its floor
    routed = clip @ planar_pose(0.0, 0.0, np.pi / 2)
    hit, m = place(env, transform_points(routed, rest))
    assert hit and min(m["crossings"]) >= rules.crossing_threshold
    # near miss: the same rope 2 cm to the side, outside the channel's openings
    hit, m = place(env, transform_points(clip @ planar_pose(0.02 + 0.01, 0.0, np.pi / 2), rest))
    assert not hit and m["crossings"] == [0, 0]
    # through one opening only: the rope's end stops in the middle of the channel
    half = transform_points(clip @ planar_pose(0.0, -0.16, np.pi / 2), rest)
    hit, m = place(env, half)
    assert not hit and m["crossings"][0] >= rules.crossing_threshold and m["crossings"][1] == 0


def test_conforms_to_gymnasium_and_is_deterministic(env):
    check_env(env, skip_render_check=True)
    actions = np.random.default_rng(0).uniform(env.action_space.low, env.action_space.high, (8, 8))
    actions[:, 3:7] = grasp_quat((1.0, 0.0))
    assert_seeded_episode_repeats(env, actions, 5, 2, "rope")
    assert env.observation_space["agent_pos"].shape == (8,) and len(env.rules.initial_states) == 27



@pytest.mark.parametrize("theta_deg", [-15.0, -10.0, 0.0, 10.0, 15.0])
@pytest.mark.parametrize("clip_y", [0.05, -0.2])
def test_expert_carries_the_rope_trailing_behind_the_hand(theta_deg, clip_y):
    """Laying a rope that lies beside the channel: while carrying, the hand turns so that the rope's body
    (at the grip, opposite the marked end) points backwards along the channel's axis, whichever way the
    folded grasp yaw pointed, turning the shorter way."""
    from twinbench.tasks.rope_expert import RopeExpert
    from twinbench.transforms import quat_to_matrix

    th = np.deg2rad(theta_deg)
    d = np.array([np.cos(th), np.sin(th), 0.0])  # the rope's direction at its marked end
    end = np.array([0.57, -0.05, 0.003])
    clip = (0.62, clip_y, 0.0)  # channel along world y: the axis runs from the rope's side towards the clip
    s = np.r_[end, end - 0.04 * d, end - 0.16 * d, clip, 0.0, 0.0]
    legs = {leg.name: leg for leg in RopeExpert(channel_length=0.035, channel_depth=0.03).plan(s)}
    axis = np.array([0.0, np.sign(clip_y - s[7]), 0.0])
    grip, carry = quat_to_matrix(legs["close"].quat), quat_to_matrix(legs["carry"].quat)
    body = carry @ grip.T @ -d  # the rope's body, turned with the hand
    np.testing.assert_allclose(body, -axis, atol=1e-9)
    turn = np.arctan2(carry[1, 0], carry[0, 0]) - np.arctan2(grip[1, 0], grip[0, 0])
    turn = (turn + np.pi) % (2 * np.pi) - np.pi
    assert abs(turn) <= np.deg2rad(90.0 + abs(theta_deg)) + 1e-9  # the shorter way round
    assert all(np.allclose(legs[k].quat, legs["carry"].quat) for k in ("lay", "drag", "lower"))


def test_expert_routes_the_centre_state(env):
    assert expert_episode(env, make_expert(env), 13)


@pytest.mark.slow
def test_expert_routes_the_whole_grid_under_the_final_rule():
    """Every grid state, full-length episodes judged on their last 100 frames (the default rule);
    benchmarks/expert_grid.py prints the same per state."""
    final = TwinEnv("rope-routing", preset="fast")
    failed = [i for i in range(27) if not expert_episode(final, make_expert(final), i)]
    assert not failed, f"the expert fails grid states {failed}"
