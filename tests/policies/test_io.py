"""policies.io: image resizing/cropping, state parts, presets, action handling (chunk-relative deltas
recover hidden absolute poses), mapping files and spec options."""

import json

import numpy as np
import pytest

from twinbench.policies import parse_policy_spec
from twinbench.policies.io import (
    PRESETS,
    ActionMap,
    ObservationMap,
    load_policy_io,
    resize_image,
    state_part,
)
from twinbench.transforms import matrix_to_quat, matrix_to_rotvec, quat_to_matrix, rotvec_to_matrix


def _obs(agent_pos, h=240, w=240):
    rng = np.random.default_rng(0)
    return {"pixels": {"front": rng.integers(0, 255, (h, w, 3), dtype=np.uint8),
                       "wrist": rng.integers(0, 255, (h, w, 3), dtype=np.uint8)},
            "agent_pos": np.asarray(agent_pos, np.float32)}


def test_resize_pad_stretch_crop_known_pixels():
    img = np.arange(2 * 4 * 3, dtype=np.uint8).reshape(2, 4, 3)
    pad = resize_image(img, (4, 4), "pad")  # scale 1: rows 1-2 hold the image, rows 0 and 3 are zero
    assert pad.shape == (4, 4, 3) and np.array_equal(pad[1:3], img)
    assert not pad[0].any() and not pad[3].any()
    wide = np.zeros((10, 20, 3), np.uint8)
    wide[:, :10] = 200  # left half bright
    crop = resize_image(wide, (10, 10), "crop")  # centre 10x10 = columns 5..14: half bright, half dark
    assert crop[:, :4].min() == 200 and crop[:, 6:].max() == 0
    assert resize_image(wide, (5, 5), "stretch").shape == (5, 5, 3)
    assert resize_image(img, (2, 4)) is img  # already the size


def test_observation_map_crop_flip_and_flat_keys():
    obs = _obs(np.zeros(2))
    om = ObservationMap(layout="flat", images={"img": "front"}, crop={"front": (10, 20, 30, 40)},
                        flip=("front",), state={"s": ("xy", "zeros:2")}, prompt_key="prompt")
    req = om.request(obs, "push")
    assert set(req) == {"img", "s", "prompt"} and req["prompt"] == "push"
    assert np.array_equal(req["img"], obs["pixels"]["front"][10:40, 20:60][::-1, ::-1])
    assert req["s"].dtype == np.float32 and req["s"].tolist() == [0, 0, 0, 0]
    with pytest.raises(ValueError, match="exceeds"):
        ObservationMap(crop={"front": (200, 0, 100, 10)}).request(obs, None)
    with pytest.raises(ValueError, match="camera 'top'"):
        ObservationMap(images={"top": "top"}).request(obs, None)
    # lerobot layout: nested, other entries pass through (a served expert's environment_state)
    req = PRESETS["lerobot"].request({**obs, "environment_state": np.ones(3)}, "t")
    assert set(req) == {"pixels", "agent_pos", "environment_state", "prompt"}
    assert req["pixels"]["front"] is obs["pixels"]["front"]


def test_state_parts_known_values():
    q = matrix_to_quat(rotvec_to_matrix(np.array([0.0, 0.0, np.pi / 2])))
    obs = _obs(np.r_[0.4, -0.1, 0.2, q, 0.25])
    assert np.allclose(state_part(obs, "ee_pos"), [0.4, -0.1, 0.2], atol=1e-6)
    assert np.allclose(state_part(obs, "ee_axis_angle"), [0, 0, np.pi / 2], atol=1e-6)
    assert np.allclose(state_part(obs, "ee_quat_xyzw"), [*q[1:], q[0]], atol=1e-6)
    assert np.allclose(state_part(obs, "gripper_fingers"), [0.03, -0.03])  # 0.08 m * (1 - 0.25) / 2
    with pytest.raises(ValueError, match="absolute or relative"):
        state_part(_obs([0.1, 0.2]), "ee_pos")
    with pytest.raises(ValueError, match="joint_position"):
        PRESETS["openpi-droid"].request(obs, "x")  # twinbench envs observe the end effector only
    assert np.array_equal(state_part({**obs, "joint_position": np.arange(7)}, "joint_position"), np.arange(7))


def test_openpi_libero_preset_request_and_actions():
    obs = _obs(np.r_[0.4, 0.0, 0.2, 1.0, 0, 0, 0, 1.0])
    io = load_policy_io("openpi-libero")
    req = io.request(obs, "pick up the block")
    assert set(req) == {"observation/image", "observation/wrist_image", "observation/state", "prompt"}
    assert req["observation/image"].shape == (224, 224, 3) and req["observation/image"].dtype == np.uint8
    assert np.allclose(req["observation/state"], [0.4, 0, 0.2, 0, 0, 0, 0, 0], atol=1e-6)
    chunk = np.zeros((10, 7))
    chunk[0] = [1, 0, -1, 0, 0.5, 0, -1]  # normalised deltas, gripper -1 = open
    chunk[1, 6] = 1.0  # close
    acts = io.actions(chunk, obs)
    assert acts.shape == (10, 7) and io.action.n_action_steps == 5
    assert np.allclose(acts[0], [0.05, 0, -0.05, 0, 0.25, 0, 0.0]) and acts[1, 6] == 1.0


def test_chunk_relative_recovers_hidden_absolute_poses():
    rng = np.random.default_rng(3)
    r0 = rotvec_to_matrix(rng.normal(size=3))
    p0 = rng.normal(size=3)
    q0 = matrix_to_quat(r0)
    obs = {"agent_pos": np.r_[p0, q0, 0.0]}
    targets_r = rotvec_to_matrix(rng.normal(size=(4, 3)))
    targets_p = rng.normal(size=(4, 3))
    dp = (targets_p - p0) @ r0  # R0^T (p - p0), in the chunk-start frame
    dr = matrix_to_rotvec(np.einsum("ji,tjk->tik", r0, targets_r))  # R0^T R
    grip = rng.uniform(size=(4, 1))
    for rotation, drot in [("axis_angle", dr), ("quat_wxyz", matrix_to_quat(rotvec_to_matrix(dr))),
                           ("quat_xyzw", matrix_to_quat(rotvec_to_matrix(dr))[:, [1, 2, 3, 0]])]:
        out = ActionMap(mode="chunk_relative", rotation=rotation).actions(np.c_[dp, drot, grip], obs)
        assert out.shape == (4, 8)
        assert np.allclose(out[:, :3], targets_p, atol=1e-5)
        assert np.allclose(quat_to_matrix(out[:, 3:7].astype(np.float64)), targets_r, atol=1e-5)
        assert np.allclose(out[:, 7], grip[:, 0], atol=1e-6)
    with pytest.raises(ValueError, match="7 entries"):
        ActionMap(mode="chunk_relative").actions(np.zeros((2, 8)), obs)


def test_mapping_file_and_errors(tmp_path):
    f = tmp_path / "my_policy.json"
    f.write_text(json.dumps({"preset": "openpi-libero", "image_size": [96, 128], "prompt": None,
                             "actions": {"n_action_steps": 3, "scale": None, "gripper": [0, 1]}}))
    io = load_policy_io(str(f))
    req = io.request(_obs(np.r_[0, 0, 0, 1, 0, 0, 0, 0]), "ignored")
    assert "prompt" not in req and req["observation/wrist_image"].shape == (96, 128, 3)
    assert (io.name, io.action.n_action_steps, io.action.dims) == ("my_policy", 3, 7)
    for bad, msg in [({"imgs": {}}, "unknown key"), ({"actions": {"steps": 2}}, "unknown actions key"),
                     ({"preset": "nope"}, "unknown preset"), ({"resize": "zoom"}, "resize"),
                     ({"actions": {"mode": "delta"}}, "mode")]:
        f.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=msg):
            load_policy_io(str(f))
    f.write_text("{not json")
    with pytest.raises(ValueError, match="not valid JSON"):
        load_policy_io(str(f))
    with pytest.raises(ValueError, match="neither a preset"):
        load_policy_io("no-such-preset")


def test_spec_options_and_labels():
    s = parse_policy_spec("pi05=remote:ws://gpu-box:8000?io=openpi-libero&n_action_steps=3")
    assert (s.name, s.target, s.checkpoint, s.io, s.n_action_steps) == (
        "pi05", "ws://gpu-box:8000", "gpu-box", "openpi-libero", 3)
    assert parse_policy_spec("remote:ws://[::1]:9000").checkpoint == "[::1]"
    s = parse_policy_spec("lerobot:out/checkpoints/005000/pretrained_model?io=cfg.json")
    assert (s.target, s.checkpoint, s.train_step, s.io) == (
        "out/checkpoints/005000/pretrained_model", "step_5000", 5000, "cfg.json")
    for bad in ["remote:ws://h:1?foo=1", "remote:ws://h:1?n_action_steps=0", "lerobot:p?io="]:
        with pytest.raises(ValueError, match="options after|n_action_steps must"):
            parse_policy_spec(bad)
