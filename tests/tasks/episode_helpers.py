"""Shared by the soft-body task tests: judging a constructed state, running an expert episode."""

import numpy as np

from twinbench.evaluation.rollout import policy_observation


def place(env, particles):
    """Put the twin's particles at `particles` and judge that frame with the task's rule."""
    env.state.physics.x.assign(np.asarray(particles, np.float32))
    return env.rules.frame(env.twin, env.state)


def expert_episode(env, expert, state: int) -> bool:
    """Run `expert` from grid state `state` to the end of the episode; the final judgement."""
    obs, info = env.reset(seed=0, options={"init_state": state})
    expert.reset()
    while True:
        obs, _, term, trunc, info = env.step(expert.select_action(policy_observation(expert, obs, info)))
        if term or trunc:
            return bool(info["is_success"])


def assert_seeded_episode_repeats(env, actions, init_state: int, seed: int, obj: str) -> None:
    """The same seed, initial state and actions give bit-identical images, state and particles."""
    runs = []
    for _ in range(2):
        obs, _ = env.reset(seed=seed, options={"init_state": init_state})
        for a in np.asarray(actions, np.float32):
            obs, *_ = env.step(a)
        runs.append([*obs["pixels"].values(), obs["agent_pos"], env.twin.particles(env.state, obj)])
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)
