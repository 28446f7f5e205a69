"""twinbench's remote client with the openpi presets against servers that answer exactly as openpi's LIBERO,
DROID and ALOHA policies do (openpi's src/openpi/policies/{libero,droid,aloha}_policy.py and the examples'
clients): the request keys, shapes and dtypes they read are checked by the server, which replies with
chunks of their configs' shapes: (10, 7) per-step end-effector deltas, (10, 8) joint velocities +
gripper position, (50, 14) absolute joint angles. Each drives episodes of a built-in gripper task."""

import threading
import traceback

import numpy as np
import pytest
from openpi_codec import pack, unpack
from scipy.spatial.transform import Rotation
from websockets.exceptions import ConnectionClosed
from websockets.sync.server import serve

from twinbench.policies import make_policy
from twinbench.policies.io import load_policy_io
from twinbench.robot.builtin import load_builtin_arm
from twinbench.tasks import get_task


def _image(x, chw=False):
    shape = (3, 224, 224) if chw else (224, 224, 3)
    assert isinstance(x, np.ndarray) and x.dtype == np.uint8 and x.shape == shape, (x.dtype, x.shape)


def _vector(x, n):
    assert isinstance(x, np.ndarray) and x.shape == (n,) and np.issubdtype(x.dtype, np.floating), x
    assert np.all(np.isfinite(x))


def _libero(obs, rng):  # LiberoInputs + make_libero_example; LiberoOutputs keeps [..., :7]
    assert set(obs) == {"observation/image", "observation/wrist_image", "observation/state", "prompt"}
    _image(obs["observation/image"]), _image(obs["observation/wrist_image"])
    _vector(obs["observation/state"], 8)
    return rng.uniform(-0.3, 0.3, (10, 7))


def _droid(obs, rng):  # DroidInputs + make_droid_example; DroidOutputs keeps [..., :8]
    assert set(obs) == {"observation/exterior_image_1_left", "observation/wrist_image_left",
                        "observation/joint_position", "observation/gripper_position", "prompt"}
    _image(obs["observation/exterior_image_1_left"]), _image(obs["observation/wrist_image_left"])
    _vector(obs["observation/joint_position"], 7), _vector(obs["observation/gripper_position"], 1)
    return np.c_[rng.uniform(-0.5, 0.5, (10, 7)), rng.uniform(0, 1, (10, 1))]


def _aloha(obs, rng):  # AlohaInputs: images {name: CHW} among EXPECTED_CAMERAS with cam_high, state 14
    assert set(obs) == {"images", "state", "prompt"}
    assert "cam_high" in obs["images"]
    assert set(obs["images"]) <= {"cam_high", "cam_low", "cam_left_wrist", "cam_right_wrist"}
    for img in obs["images"].values():
        _image(img, chw=True)
    _vector(obs["state"], 14)
    state = np.asarray(obs["state"], np.float64)
    assert np.all(state[7:] == 0) and 0 <= state[6] <= 1  # the right arm absent, gripper 1 = open
    return np.tile(state, (50, 1)) + np.c_[rng.uniform(-0.05, 0.05, (50, 6)), np.zeros((50, 8))]


class OpenpiServer:
    """openpi's WebsocketPolicyServer protocol: metadata first, one reply per request with `actions` and
    `server_timing`, a traceback text frame + close 1011 on an error."""

    def __init__(self, answer):
        self.answer, self.requests, self.errors = answer, [], []
        self._rng = np.random.default_rng(0)
        self._server = serve(self._handle, "127.0.0.1", 0, compression=None, max_size=None)
        self.url = f"ws://127.0.0.1:{self._server.socket.getsockname()[1]}"
        threading.Thread(target=self._server.serve_forever, daemon=True).start()

    def _handle(self, ws):
        ws.send(pack({}))
        while True:
            try:
                obs = unpack(ws.recv())
            except ConnectionClosed:
                return
            try:
                self.requests.append(obs)
                actions = self.answer(obs, self._rng)
                ws.send(pack({"actions": actions, "server_timing": {"infer_ms": 1.0}}))
            except Exception:  # noqa: BLE001 - reported to the client as openpi does
                self.errors.append(traceback.format_exc())
                ws.send(self.errors[-1])
                ws.close(1011, "Internal server error. Traceback included in previous frame.")
                return

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self._server.shutdown()


@pytest.mark.parametrize("preset, answer, task, n_action_steps", [
    ("openpi-libero", _libero, "toy-packing", 5),
    ("openpi-droid", _droid, "rope-routing", 8),
    ("openpi-aloha", _aloha, "toy-packing", 25),
])
def test_openpi_policies_run_episodes_on_builtin_tasks(preset, answer, task, n_action_steps):
    spec = get_task(task)
    env = spec.make_env(preset="fast", episode_seconds=0.5, settle_steps=0)  # 15 steps
    with OpenpiServer(answer) as server:
        policy = make_policy(f"remote:{server.url}?io={preset}", spec, env)
        policy.warm_up()
        steps = 0
        for episode in range(2):
            obs, _ = env.reset(seed=episode)
            policy.reset()
            done = False
            while not done:
                action = policy.select_action(obs)
                assert env.action_space.contains(action) or np.allclose(
                    np.clip(action, env.action_space.low, env.action_space.high), action, atol=1e-3), action
                obs, _, terminated, truncated, info = env.step(action)
                assert info["status"] == "ok"
                done = terminated or truncated
                steps += 1
        policy.close()
        assert server.errors == []
        assert steps == 30 and len(server.requests) == 2 * -(-15 // n_action_steps)
        assert all(r["prompt"] == env.unwrapped.task_description for r in server.requests)
    env.close()


def _obs_at(robot, q_arm, gripper=0.0):
    q = robot.home_q.copy()
    q[robot.arm_q_indices] = q_arm
    t = robot.ee_pose(q)
    quat = Rotation.from_matrix(t[:3, :3]).as_quat()[[3, 0, 1, 2]]
    quat *= -1.0 if quat[0] < 0 else 1.0  # as the env's agent_pos: w >= 0
    return {"agent_pos": np.r_[t[:3, 3], quat, gripper], "joint_position": np.asarray(q_arm, np.float32),
            "gripper_position": np.array([gripper], np.float32)}


def test_libero_step_delta_applies_each_delta_to_the_pose_of_its_step():
    io = load_policy_io("openpi-libero")
    rot0 = Rotation.from_rotvec([0.3, -0.2, 1.0])
    obs = {"agent_pos": np.r_[0.4, 0.1, 0.2, rot0.as_quat()[[3, 0, 1, 2]], 0.0]}
    chunk = np.array([[1, 0, -1, 0, 0.5, 0, 1.0], [0, 0.2, 0, 0, 0, 0, -1.0]])
    queued = io.actions(chunk, obs)  # scaled (0.05 m, 0.5 rad) and gripper [-1, 1] -> [0, 1]
    assert np.allclose(queued[0], [0.05, 0, -0.05, 0, 0.25, 0, 1.0], atol=1e-6)
    out = io.step(queued[0], obs)
    assert np.allclose(out[:3], [0.45, 0.1, 0.15], atol=1e-6) and out[7] == 1.0
    want = Rotation.from_rotvec([0, 0.25, 0]) * rot0  # base-frame delta, applied on the left
    assert Rotation.from_quat(out[[4, 5, 6, 3]]).approx_equal(want, atol=1e-6)
    moved = {"agent_pos": np.r_[0.5, 0.0, 0.3, 1.0, 0, 0, 0, 1.0]}  # the second delta: from its own step
    assert np.allclose(io.step(queued[1], moved), [0.5, 0.01, 0.3, 1, 0, 0, 0, 0.0], atol=1e-6)


def test_droid_joint_velocity_and_aloha_joint_position_reach_their_joint_targets():
    robot = load_builtin_arm("gripper", load_meshes=False)
    q_arm = robot.home_q[robot.arm_q_indices]
    obs = _obs_at(robot, q_arm)
    droid = load_policy_io("openpi-droid").action
    v = np.array([1.0, -0.5, 0, 0, 2.0, 0, 0, 0.7])  # v clipped to [-1, 1]; gripper binarised at 0.5
    queued = droid.actions(v[None], obs)[0]
    out = droid.step(queued, obs, robot)
    want = _obs_at(robot, q_arm + 0.1 * np.r_[1.0, -0.5, 0, 0, 1.0, 0, 0])["agent_pos"]
    assert np.allclose(out[:7], want[:7], atol=1e-5) and out[7] == 1.0
    aloha = load_policy_io("openpi-aloha")
    target = q_arm[:6] + 0.05
    reply = np.zeros((50, 14))
    reply[:, :6], reply[:, 6] = target, 0.25  # ALOHA gripper 0.25 open -> 0.75 closed
    queued = aloha.actions(reply, obs)
    assert queued.shape == (50, 7)
    out = aloha.action.step(queued[0], obs, robot)
    want = _obs_at(robot, np.r_[target, q_arm[6]])["agent_pos"]  # the 7th joint held where it is
    assert np.allclose(out[:7], want[:7], atol=1e-5) and np.isclose(out[7], 0.75)
    with pytest.raises(ValueError, match="robot"):
        aloha.action.step(queued[0], obs, None)


def test_aloha_request_nests_images_channels_first_and_pads_the_state():
    robot = load_builtin_arm("gripper", load_meshes=False)
    q_arm = robot.home_q[robot.arm_q_indices] + np.arange(7) * 0.01
    rng = np.random.default_rng(1)
    obs = {**_obs_at(robot, q_arm, gripper=0.25),
           "pixels": {c: rng.integers(0, 255, (120, 160, 3), dtype=np.uint8) for c in ("front", "wrist")}}
    req = load_policy_io("openpi-aloha").request(obs, "fold")
    assert set(req) == {"images", "state", "prompt"} and set(req["images"]) == {"cam_high", "cam_left_wrist"}
    img = req["images"]["cam_high"]
    assert img.shape == (3, 224, 224) and img.dtype == np.uint8
    # pad: 160 -> 224 wide, 120 -> 168 high, centred (28 rows of zeros above)
    assert np.all(img[:, :28] == 0) and img[:, 28:196].any()
    assert req["state"].dtype == np.float32
    assert np.allclose(req["state"], np.r_[q_arm[:6], 0.75, np.zeros(7)], atol=1e-6)
