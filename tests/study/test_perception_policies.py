"""Perception controllers (twinbench.study.policies): the T's pose estimated from the front camera image of
the push-T fast cell, against the true pose (known answers), and the config file's checks."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.errors import InputError
from twinbench.study import policies as P

POS_TOL_M = 0.008  # measured: <= 5 mm on the 16 grid states
ANGLE_TOL_RAD = np.deg2rad(3.0)  # measured: <= 2.5 deg


@pytest.fixture(scope="module")
def scene():
    from twinbench.tasks import get_task

    env = get_task("push-t").make_env(preset="fast", environment_state=True)
    u = env.unwrapped
    cam = u.twin.camera(u.state, "front")
    frames = {}
    for i in (0, 6, 9, 15):
        obs, _ = env.reset(seed=0, options={"init_state": i})
        frames[i] = (obs["pixels"]["front"], np.asarray(obs["environment_state"][:3], np.float64))
    yield u, cam, frames
    env.close()


def _colors(u, cam, frames, state=0):
    """The colour model from one labelled image (the block's pixels from its known pose)."""
    overlay = P._overlay(u, "front")
    probe = P.TPoseEstimator(u.rules.outline, cam, {"plain": {"mean": [0, 0, 0], "cov": np.eye(3).tolist()}})
    img, pose = frames[state]
    mask = P.label_mask(probe, pose)
    return P.fit_colors({"plain": [img[mask & ~overlay]], "overlay": [img[mask & overlay]]})


def _angle(a: float) -> float:
    return abs((a + np.pi) % (2 * np.pi) - np.pi)


def test_pose_from_clean_images_matches_the_true_pose(scene):
    u, cam, frames = scene
    est = P.TPoseEstimator(u.rules.outline, cam, _colors(u, cam, frames), overlay=P._overlay(u, "front"))
    for i in (6, 9, 15):  # states the colours were not fitted on: 3 positions, 3 headings of the grid
        img, true = frames[i]
        got = est.estimate(img)
        assert got is not None, i
        assert np.linalg.norm(got[:2] - true[:2]) < POS_TOL_M, (i, got, true)
        assert _angle(got[2] - true[2]) < ANGLE_TOL_RAD, (i, got, true)
        tracked = est.estimate(img, previous=true + [0.01, -0.01, 0.15])  # tracking from a stale estimate
        assert np.linalg.norm(tracked[:2] - true[:2]) < POS_TOL_M
        assert _angle(tracked[2] - true[2]) < ANGLE_TOL_RAD


def test_wrong_colours_are_not_seen(scene):
    """An image whose colours are off (red +60 levels, as a twin without colour alignment may render) loses
    the block: what makes a twin's appearance matter to these policies."""
    u, cam, frames = scene
    est = P.TPoseEstimator(u.rules.outline, cam, _colors(u, cam, frames), overlay=P._overlay(u, "front"))
    img, _ = frames[6]
    assert est.segment(img).sum() > 1000
    off = np.clip(img.astype(int) + [60, 0, 0], 0, 255).astype(np.uint8)
    assert est.segment(off).sum() < est.min_pixels
    assert est.estimate(off) is None


def test_config_round_trip_and_errors(tmp_path):
    cfgs = P.levels({"plain": {"mean": [1, 2, 3], "cov": np.eye(3).tolist()}})
    assert len(cfgs) >= 8
    path = P.write_config(cfgs["p3-lag15"], tmp_path / "p.json")
    assert P.read_config(path) == cfgs["p3-lag15"]
    (tmp_path / "bad.json").write_text('{"colors": {}, "gain": 0}')
    with pytest.raises(InputError, match="gain must be > 0"):
        P.read_config(tmp_path / "bad.json")
    (tmp_path / "odd.json").write_text('{"colours": {}}')
    with pytest.raises(InputError, match="colors"):
        P.read_config(tmp_path / "odd.json")
    with pytest.raises(InputError, match="does not exist"):
        P.read_config(tmp_path / "missing.json")


def test_policy_kind_parses_through_the_registry(monkeypatch):
    from twinbench.policies import spec as spec_module

    monkeypatch.setattr(spec_module, "POLICY_KINDS", dict(spec_module.POLICY_KINDS))  # loading registers it
    spec = spec_module.parse_policy_spec("p0=perceive:/some/where/p0.json")
    assert (spec.kind, spec.name, spec.target) == ("perceive", "p0", "/some/where/p0.json")


def test_controller_acts_like_the_expert_on_the_true_pose_and_reseeds(scene):
    """The clean controller's first action is the expert's on the true pose within the estimate's error;
    a noisy one repeats its actions after `reseed` with the same seed and changes them with another."""
    from twinbench.tasks.push_t import make_expert

    u, cam, frames = scene
    env = u  # the controllers take an env (`unwrapped` of the unwrapped env is itself)
    colors = _colors(u, cam, frames)
    obs, _ = u.reset(seed=0, options={"init_state": 9})
    clean = P.PerceptionPushT(env, P.PerceptionConfig(colors=colors, camera_model=P.camera_dict(cam)))
    expert = make_expert(env)
    state = {"agent_pos": obs["agent_pos"], "environment_state": obs["environment_state"]}
    want = expert.select_action(state)
    got = clean.select_action(obs)
    assert np.linalg.norm(np.asarray(got, np.float64) - np.asarray(want, np.float64)) < 0.02

    noisy = P.PerceptionPushT(env, P.PerceptionConfig(colors=colors, noise_m=0.02, noise_rad=0.1), seed=3)

    def first_actions(seed):
        noisy.reseed(seed)
        return np.array([noisy.select_action(obs) for _ in range(3)])

    a, b, c = first_actions(3), first_actions(3), first_actions(4)
    assert np.array_equal(a, b)
    assert not np.array_equal(a, c)
