"""Measured kinematic inputs (control points' paths, a tool's poses) are smoothed before sysid simulates them
where they are noisy (`sysid_guess.smoothed_inputs`): known noise is estimated, the true physics then tracks
its own motion closer to the noise floor, and noise-free inputs are simulated exactly as given."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from twinbench.construct.sysid_family import family_case
from twinbench.construct.sysid_synthetic import phystwin_rope_case, pushed_block_case, synthetic_case
from twinbench.physics.sysid import FitConfig, LossWeights, SequenceLoss, build_model, evaluate, identify
from twinbench.physics.sysid_guess import MIN_INPUT_NOISE, difference_noise, smoothed_inputs

NOISE = 5e-4  # m per axis: the study's evidence puts this much on the tool's and the probe's paths


def _smoothstep(t: np.ndarray, a: float, b: float) -> np.ndarray:
    u = np.clip((t - a) / (b - a), 0.0, 1.0)
    return u * u * (3.0 - 2.0 * u)


def _errors(data, truth, log_y=None) -> tuple[float, float]:
    model = build_model(data, truth["params"], truth["sim"])
    if log_y is not None:
        model.set_spring_log_y(log_y)
    ev = evaluate(model, data, SequenceLoss(data, LossWeights()))
    return ev.train_error, ev.val_error


def _noisy_tool_block():
    """The pushed block case, and the same with NOISE on its tool's recorded positions."""
    data, truth = pushed_block_case(seed=0)
    poses = data.tool_poses.copy()
    poses[:, :3, 3] += np.random.default_rng(10).normal(0.0, NOISE, poses[:, :3, 3].shape)
    return data, truth, replace(data, tool_poses=poses)


@pytest.mark.parametrize("order", [2, 3, 4])
def test_difference_noise_recovers_white_noise_on_a_moving_path(order):
    rng = np.random.default_rng(order)
    t = np.arange(45) / 30.0
    path = np.stack([0.05 * _smoothstep(t, 0.1, 1.1), 0.06 * _smoothstep(t, 0.1, 1.1), 0.005 + 0 * t], 1)
    series = path[:, None, :] + rng.normal(0.0, NOISE, (45, 8, 3))
    assert difference_noise(series, order) == pytest.approx(NOISE, rel=0.15)


def test_fourth_differences_see_no_noise_in_exact_paths_with_kinks_or_fast_motion():
    t = np.arange(45) / 30.0
    kinked = np.stack([np.clip(t - 0.5, 0.0, None), np.abs(t - 0.8), 0 * t], 1)
    fast = np.stack([0.3 * _smoothstep(t, 0.2, 0.5), 0.05 * np.sin(2 * np.pi * 2 * t), 0 * t], 1)
    for path in (kinked, fast):
        assert difference_noise(path, 4) < 0.2 * MIN_INPUT_NOISE


def test_noise_free_inputs_are_simulated_exactly_as_given():
    cases = [family_case(i, 0)[0] for i in range(0, 12, 3)]
    cases += [synthetic_case()[0], phystwin_rope_case()[0], pushed_block_case()[0]]
    for data in cases:
        out, report = smoothed_inputs(data)
        assert out is data
        assert report and not any(r["smoothed"] for r in report.values())
        assert all(r["rms_change"] == 0.0 for r in report.values())


def test_noisy_tool_poses_are_smoothed_and_the_true_physics_tracks_its_motion_again():
    data, truth, noisy = _noisy_tool_block()
    smoothed, report = smoothed_inputs(noisy)
    r = report["tool_translation"]
    assert r["smoothed"] and r["noise"] == pytest.approx(NOISE, rel=0.3)
    assert not report["tool_rotation"]["smoothed"]  # the tool does not turn
    exact = data.tool_poses[:, :3, 3]
    assert np.sqrt(np.mean((smoothed.tool_poses[:, :3, 3] - exact) ** 2)) < 0.6 * NOISE
    clean, before, after = _errors(data, truth), _errors(noisy, truth), _errors(smoothed, truth)
    # the tool's jitter moves the block: at its own physics it tracks worse than the tracks' noise floor
    assert before[0] > clean[0] + 3e-4 and before[1] > clean[1] + 5e-4
    assert after[0] < clean[0] + 1.5e-4 and after[1] < clean[1] + 1.5e-4


def test_noisy_control_paths_are_smoothed():
    data, truth = phystwin_rope_case(seed=0)
    before, after = [], []
    for draw in range(4):  # the rope folds when lowered: one draw's held-out frames are chaotic, a mean less
        rng = np.random.default_rng(100 + draw)
        noisy = replace(data, controls=data.controls + rng.normal(0.0, NOISE, data.controls.shape))
        smoothed, report = smoothed_inputs(noisy)
        r = report["controls"]
        assert r["smoothed"] and r["noise"] == pytest.approx(NOISE, rel=0.2)
        # the pieces of the hand's path round a little
        assert np.sqrt(np.mean((smoothed.controls - data.controls) ** 2)) < 0.75 * NOISE
        before.append(_errors(noisy, truth, truth["log_y"]))
        after.append(_errors(smoothed, truth, truth["log_y"]))
    gain = np.mean(before, axis=0) - np.mean(after, axis=0)  # (fitted, held-out) frames
    assert gain[0] > 4e-4 and gain[1] > 5e-4


def test_a_tool_turning_through_full_turns_is_smoothed_on_one_hemisphere():
    data, _ = pushed_block_case(seed=0)
    n = data.num_frames
    angle = 4.0 * np.pi * np.arange(n) / (n - 1)  # two full turns: quaternions cross hemispheres
    exact = Rotation.from_rotvec(np.outer(angle, [0.0, 0.0, 1.0]))
    rng = np.random.default_rng(12)
    noisy_rot = Rotation.from_rotvec(rng.normal(0.0, 3e-3, (n, 3))) * exact
    poses = data.tool_poses.copy()
    poses[:, :3, :3] = noisy_rot.as_matrix()
    smoothed, report = smoothed_inputs(replace(data, tool_poses=poses))
    assert report["tool_rotation"]["smoothed"]
    assert report["tool_rotation"]["noise"] == pytest.approx(3e-3, rel=0.3)
    rot = smoothed.tool_poses[:, :3, :3]
    np.testing.assert_allclose(np.einsum("fij,fkj->fik", rot, rot), np.broadcast_to(np.eye(3), rot.shape),
                               atol=1e-9)
    err_after = (Rotation.from_matrix(rot) * exact.inv()).magnitude()
    err_before = (noisy_rot * exact.inv()).magnitude()
    assert np.sqrt(np.mean(err_after ** 2)) < 0.6 * np.sqrt(np.mean(err_before ** 2))


def test_identify_simulates_the_smoothed_inputs_and_reports_them():
    data, truth, noisy = _noisy_tool_block()
    cfg = FitConfig(stage1=False, stage2=False, stage3=False, initial=truth["params"], progress=False)
    on = identify(noisy, cfg, base=truth["sim"], log=lambda _m: None)
    off = identify(noisy, replace(cfg, smooth_inputs=False), base=truth["sim"], log=lambda _m: None)
    assert on.inputs["tool_translation"]["smoothed"] and "tool_translation" not in off.inputs
    assert on.evals["final"].train_error == pytest.approx(_errors(smoothed_inputs(noisy)[0], truth)[0],
                                                          rel=1e-6)
    assert off.evals["final"].train_error == pytest.approx(_errors(noisy, truth)[0], rel=1e-6)
    assert on.evals["final"].train_error < off.evals["final"].train_error - 3e-4


def test_particles_below_the_ground_are_raised_onto_it():
    """A particle that starts below the ground and moves down is put back onto it from a time of impact far in
    the past (PhysTwin's ground contact), which throws it sideways by its velocity times that time: the
    block, its bottom layer measured up to ~1.5 mm below the ground, is pushed along another path at its own
    physics unless those particles are raised onto the ground (here: exactly where they were)."""
    from twinbench.physics.sysid_guess import grounded

    data, truth = pushed_block_case(seed=0)
    bottom = data.particles[:, 2] == 0.0
    clean = _errors(data, truth)
    worse = []
    for seed in range(2):
        rng = np.random.default_rng(seed)
        sunk = data.particles.copy()
        sunk[bottom, 2] = -np.abs(rng.normal(0.0, NOISE, bottom.sum()))
        measured = replace(data, particles=sunk)
        fixed, report = grounded(measured)
        assert report == {"below": int(bottom.sum()), "of": len(sunk), "deepest": -sunk[:, 2].min()}
        np.testing.assert_array_equal(fixed.particles, data.particles)
        worse.append(np.subtract(_errors(measured, truth), clean))
    assert np.mean(worse, axis=0)[0] > 1e-3 and np.mean(worse, axis=0)[1] > 3e-3
    assert grounded(data)[0] is data  # none below: as given
    cfg = FitConfig(stage1=False, stage2=False, stage3=False, initial=truth["params"], progress=False)
    result = identify(measured, cfg, base=truth["sim"], log=lambda _m: None)
    assert result.inputs["particles_below_ground"] == report
    assert result.evals["final"].train_error == pytest.approx(clean[0], rel=1e-6)
    assert (result.model.x0_np[:, 2] >= 0.0).all()
    off = identify(measured, replace(cfg, ground=False), base=truth["sim"], log=lambda _m: None)
    assert "particles_below_ground" not in off.inputs


def test_particles_far_below_the_ground_are_an_error_of_the_data():
    from twinbench.physics.sysid_data import SysIdFormatError
    from twinbench.physics.sysid_guess import grounded

    data, _ = pushed_block_case(seed=0)
    sunk = replace(data, particles=data.particles - np.array([0.0, 0.0, 0.03]))
    with pytest.raises(SysIdFormatError, match=r"particles.*below the ground.*30\.0 mm.*--no-ground"):
        grounded(sunk)
