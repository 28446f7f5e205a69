"""CameraResponse: identity leaves images alone, known colours map to hand-computed values, noise is
reproducible per seed; twin.json round trip; TwinEnv applies a camera's response to its images."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twinbench.gaussians.response import CameraResponse
from twinbench.twin import load_twin, save_twin
from twinbench.twin.cells import push_t_cell
from twinbench.twin.files import TwinFormatError


def _image(value, hw=(8, 10)) -> np.ndarray:
    return np.full((*hw, 3), value, np.uint8)


def test_identity_is_unchanged():
    img = np.random.default_rng(0).integers(0, 256, (12, 9, 3), dtype=np.uint8)
    r = CameraResponse()
    assert r.is_identity
    assert np.array_equal(r.apply(img), img)
    # an identity given explicitly (every field at its neutral value) too
    r2 = CameraResponse.from_dict(CameraResponse().to_dict())
    assert r2.is_identity and np.array_equal(r2.apply(img), img)


def test_known_matrix_offset_gamma():
    r = CameraResponse(matrix=np.diag([0.5, 1.0, 0.25]), offset=[0.1, 0.0, 0.0], gamma=2.0)
    out = r.apply(_image(102))  # 102 / 255 = 0.4
    # R (0.5 * 0.4 + 0.1)^2 = 0.09 -> 22.95; G 0.4^2 = 0.16 -> 40.8; B (0.25 * 0.4)^2 = 0.01 -> 2.55
    assert out[0, 0].tolist() == [23, 41, 3]
    assert np.all(out == out[0, 0])
    # white balance gains act before the matrix; a cross-channel matrix mixes channels
    wb = CameraResponse(white_balance=[2.0, 1.0, 0.5], matrix=[[0, 1, 0], [1, 0, 0], [0, 0, 1]])
    assert wb.apply(_image(102))[0, 0].tolist() == [102, 204, 51]


def test_vignetting_and_blur():
    r = CameraResponse(vignetting=0.4)
    out = r.apply(_image(200, (9, 9)))
    assert out[4, 4].tolist() == [200] * 3  # the centre keeps its colour
    assert out[0, 0].tolist() == [120] * 3  # a corner loses 40 %
    edge = np.zeros((9, 9, 3), np.uint8)
    edge[:, 5:] = 255
    blurred = CameraResponse(blur_sigma=1.0).apply(edge)
    assert 0 < blurred[4, 4, 0] < 128 < blurred[4, 5, 0] < 255  # the step is smoothed, symmetric
    assert int(blurred[4, 4, 0]) + int(blurred[4, 5, 0]) == pytest.approx(255, abs=1)


def test_noise_reproducible_per_seed():
    r = CameraResponse(noise_std=4.0)
    img = _image(128, (64, 64))
    a = r.apply(img, np.random.default_rng(3))
    b = r.apply(img, np.random.default_rng(3))
    c = r.apply(img, np.random.default_rng(4))
    assert np.array_equal(a, b) and not np.array_equal(a, c)
    assert a.astype(float).std() == pytest.approx(4.0, rel=0.1)
    with pytest.raises(ValueError, match="rng"):
        r.apply(img)


def test_bad_values_named():
    with pytest.raises(ValueError, match="gamma"):
        CameraResponse(gamma=-1.0)
    with pytest.raises(ValueError, match="matrix"):
        CameraResponse(matrix=np.eye(4))
    with pytest.raises(ValueError, match="unknown field"):
        CameraResponse.from_dict({"gain": 2})


def test_twin_json_round_trip(tmp_path):
    spec = push_t_cell("fast")
    resp = CameraResponse(matrix=np.diag([0.9, 1.0, 1.1]), gamma=1.2, vignetting=0.1, noise_std=2.0)
    front = dataclasses.replace(spec.cameras[0], response=resp)
    save_twin(dataclasses.replace(spec, cameras=(front, *spec.cameras[1:])), tmp_path / "t")
    back = load_twin(tmp_path / "t")
    assert back.cameras[0].response.to_dict() == resp.to_dict()
    assert back.cameras[1].response is None
    # old files (no "response") load: the plain cell's file has none
    save_twin(spec, tmp_path / "plain")
    assert '"response"' not in (tmp_path / "plain/twin.json").read_text()
    assert all(c.response is None for c in load_twin(tmp_path / "plain").cameras)
    bad = (tmp_path / "t/twin.json").read_text().replace('"gamma": 1.2', '"gamma": -3')
    (tmp_path / "t/twin.json").write_text(bad)
    with pytest.raises(TwinFormatError, match=r"cameras\[0\]\(front\)\.response: camera response\.gamma"):
        load_twin(tmp_path / "t")


@pytest.mark.timeout(120)
def test_env_applies_the_response():
    from twinbench.env import TwinEnv

    spec = push_t_cell("fast")
    resp = CameraResponse(matrix=[[0.8, 0.1, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.0]], offset=[0.02, 0, 0],
                          gamma=1.3)
    real = dataclasses.replace(spec, cameras=(dataclasses.replace(spec.cameras[0], response=resp),
                                              *spec.cameras[1:]))
    plain_env = TwinEnv("push-t", twin=spec)
    real_env = TwinEnv("push-t", twin=real)
    p, _ = plain_env.reset(seed=0)
    q, _ = real_env.reset(seed=0)
    assert np.array_equal(q["pixels"]["front"], resp.apply(p["pixels"]["front"]))
    assert np.array_equal(q["pixels"]["wrist"], p["pixels"]["wrist"])  # no response on the wrist camera
    assert np.array_equal(real_env.render(), q["pixels"]["front"])  # render() shows what the policy sees
    # noise drawn from the reset seed: the same seed gives the same images, another seed others
    noisy = dataclasses.replace(spec, cameras=(dataclasses.replace(spec.cameras[0],
                                                                   response=CameraResponse(noise_std=3.0)),
                                               *spec.cameras[1:]))
    env = TwinEnv("push-t", twin=noisy)
    a = env.reset(seed=5, options={"init_state": 0})[0]["pixels"]["front"].copy()
    b = env.reset(seed=5, options={"init_state": 0})[0]["pixels"]["front"].copy()
    c = env.reset(seed=6, options={"init_state": 0})[0]["pixels"]["front"].copy()
    assert np.array_equal(a, b) and not np.array_equal(a, c)
