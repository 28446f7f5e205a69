"""The LeRobot observation mapping (numpy part; running a real LeRobot policy needs the lerobot extra)."""

import numpy as np
import pytest

from twinbench.policies.lerobot_adapter import lerobot_arrays
from twinbench.tasks import get_task


def test_observation_mapping_known_values():
    front = np.zeros((2, 3, 3), np.uint8)
    front[0, 1] = (255, 51, 0)  # row 0, column 1
    obs = {"pixels": {"front": front, "wrist": np.full((2, 3, 3), 102, np.uint8)},
           "agent_pos": np.array([0.1, -0.2], np.float32)}
    b = lerobot_arrays(obs, "push the T")
    f = b["observation.images.front"]
    assert f.shape == (1, 3, 2, 3) and f.dtype == np.float32
    assert f[0, :, 0, 1].tolist() == pytest.approx([1.0, 0.2, 0.0]) and f[0, :, 1, 1].tolist() == [0, 0, 0]
    assert np.allclose(b["observation.images.wrist"], 0.4)
    assert b["observation.state"].shape == (1, 2) and b["observation.state"][0, 1] == np.float32(-0.2)
    assert b["task"] == ["push the T"]
    env = get_task("point-reach").make_env()
    b = lerobot_arrays(env.reset(seed=0)[0], "")
    assert set(b) == {"observation.images.front", "observation.images.wrist", "observation.state", "task"}
    with pytest.raises(ValueError, match="uint8"):
        lerobot_arrays({"pixels": {"front": np.zeros((2, 2, 3))}, "agent_pos": np.zeros(2)}, "")
