"""What the websocket tests share: a policy to serve (`Doubler`), and a LIBERO-like openpi exchange (the
env text a remote policy reads, an observation, the action chunk a server answers and the actions
twinbench's `openpi-libero` layout makes of it)."""

import numpy as np
from scipy.spatial.transform import Rotation

CHUNK = np.linspace(-1, 1, 70, dtype=np.float32).reshape(10, 7)  # a LIBERO model's 10 x 7 action chunk


class Doubler:
    def reset(self):
        pass

    def select_action(self, obs):
        if obs.get("prompt") == "crash":
            raise ValueError("bad observation")
        return 2 * np.asarray(obs["agent_pos"], np.float32)


class Env:
    """What make_policy reads from an env: the task text."""

    class unwrapped:  # noqa: N801
        task_description = "put the bowl on the plate"


def libero_obs():
    rng = np.random.default_rng(0)
    return {"pixels": {c: rng.integers(0, 255, (240, 320, 3), dtype=np.uint8) for c in ("front", "wrist")},
            "agent_pos": np.array([0.4, 0, 0.2, 1, 0, 0, 0, 0.0], np.float32)}


def libero_actions(obs):
    """The actions `openpi-libero` makes of CHUNK from `obs`: per-step deltas from the observed pose
    (identity rotation), [p + dp, quat(dr), gripper [-1, 1] -> [0, 1]]."""
    delta = CHUNK * np.r_[[0.05] * 3, [0.5] * 3, 1.0]
    delta[:, 6] = (CHUNK[:, 6] + 1) / 2
    quat = Rotation.from_rotvec(delta[:, 3:6]).as_quat()[:, [3, 0, 1, 2]]
    quat *= np.where(quat[:, :1] < 0, -1.0, 1.0)
    return np.c_[obs["agent_pos"][:3] + delta[:, :3], quat, delta[:, 6]]


def check_libero_exchange(url: str, requests: list) -> None:
    """twinbench's `remote:` client with the `openpi-libero` layout against a LIBERO-like server at `url` that
    answers CHUNK and raises "model exploded" on the prompt "crash" (`requests`: what it received)."""
    import pytest

    from twinbench.policies import PolicyError, make_policy
    from twinbench.tasks import get_task

    pol = make_policy(f"pi05=remote:{url}?io=openpi-libero", get_task("point-reach"), Env())
    obs = libero_obs()
    got = np.array([pol.select_action(obs) for _ in range(7)])
    assert len(requests) == 2  # 5 of each 10-action chunk executed (openpi's replan_steps)
    req = requests[0]
    assert set(req) == {"observation/image", "observation/wrist_image", "observation/state", "prompt"}
    assert req["prompt"] == "put the bowl on the plate" and req["observation/image"].dtype == np.uint8
    expected = libero_actions(obs)
    assert np.allclose(got, np.r_[expected[:5], expected[:2]], atol=1e-6)
    pol.close()
    pol = make_policy(f"remote:{url}?io=openpi-libero", get_task("point-reach"), Env())
    pol.prompt = "crash"
    with pytest.raises(PolicyError, match="model exploded"):
        pol.select_action(obs)
    pol.close()
