"""Shared by the soft-body task tests: judging a constructed state, running an expert episode."""

import numpy as np

from twinbench.evaluation.runner import policy_observation


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
