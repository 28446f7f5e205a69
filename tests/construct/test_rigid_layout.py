"""rigid_layout: a rigid body's tracked motion carried onto another layout of it recovers the known motion
(noise and unreliable tracks included) and moves every particle of the new layout with it."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from twinbench.construct.rigid_layout import relayout, rigid_motion
from twinbench.physics.sysid_data import SysIdData, SysIdFormatError
from twinbench.transforms import planar_pose, rotation_angle, transform_points


def _case(noise=0.001, seed=0):
    """A T-sized body (points in a 15 x 15 x 3 cm box) sliding and turning on the ground over 20 frames,
    tracked at 40 of its 60 points with `noise` (m), 4 tracks off by 2-4 cm in every frame, and frame 7
    seen by 2 tracks only."""
    rng = np.random.default_rng(seed)
    body = rng.uniform([0.35, -0.075, 0.0], [0.5, 0.075, 0.03], (60, 3))
    truth = np.stack([planar_pose(0.004 * k, 0.003 * k, np.radians(1.5 * k)) for k in range(20)])
    moved = transform_points(truth, body)  # (20, 60, 3)
    idx = np.arange(0, 60, 60 // 40)[:40]
    tracked = moved[:, idx] + rng.normal(0, noise, (20, len(idx), 3))
    tracked[1:, :4] += rng.uniform(0.02, 0.04, (19, 4, 3)) * rng.choice([-1, 1], (19, 4, 3))
    valid = np.ones((20, len(idx)), bool)
    valid[7, 2:] = False
    data = SysIdData(particles=body, observed=moved, visibility=np.ones((20, 60), bool), tracked_indices=idx,
                     tracked=tracked, motion_valid=valid, controls=np.zeros((20, 0, 3)), masses=np.ones(60))
    return data, truth


def test_rigid_motion_recovers_the_known_motion_despite_noise_and_bad_tracks():
    data, truth = _case()
    poses, ok = rigid_motion(data)
    assert ok.tolist() == [k != 7 for k in range(20)]  # two tracks cannot fix a frame's motion
    for k in np.flatnonzero(ok):  # the body where the fitted motion puts it: within the tracks' noise
        err = np.linalg.norm(transform_points(poses[k], data.particles)
                             - transform_points(truth[k], data.particles), axis=1)
        assert err.mean() < 1e-3 and err.max() < 2.5e-3
        assert np.degrees(rotation_angle(poses[k][:3, :3], truth[k][:3, :3])) < 1.0  # a 3 cm tall body tilts
    # without the trimming pass the 4 bad tracks (of 40) pull the fit off by centimetres
    from twinbench.transforms import fit_rigid_transform

    plain = fit_rigid_transform(data.tracked[0], data.tracked[5])
    assert np.linalg.norm(transform_points(plain, data.particles)
                          - transform_points(truth[5], data.particles), axis=1).mean() > 2e-3


def test_relayout_moves_every_particle_of_the_new_layout_with_the_body():
    data, truth = _case()
    # another layout of the same body: a 1 cm lattice over its box, at frame 0
    axes = [np.arange(lo, hi + 1e-9, 0.01) for lo, hi in ((0.35, 0.5), (-0.075, 0.075), (0.0, 0.03))]
    lattice = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    out = relayout(data, lattice, np.full(len(lattice), 0.5))
    assert np.array_equal(out.particles, lattice)
    assert out.tracked_indices.tolist() == list(range(len(lattice)))
    assert out.masses.tolist() == [0.5] * len(lattice) and out.springs is None
    expected = transform_points(truth, lattice)
    seen = out.motion_valid[:, 0]
    assert not seen[7] and seen.sum() == 19
    assert np.abs(out.tracked[seen] - expected[seen]).max() < 4e-3  # the lattice's far corners, 1 mm noise
    assert np.median(np.linalg.norm(out.tracked[seen] - expected[seen], axis=2)) < 1e-3
    assert np.array_equal(out.observed, data.observed)  # what was seen stays


def test_relayout_needs_tracks_at_frame_0():
    data, _ = _case()
    valid = data.motion_valid.copy()
    valid[0, 2:] = False
    bad = dataclasses.replace(data, motion_valid=valid, source="motion/x")
    with pytest.raises(SysIdFormatError, match="motion/x.*frame 0"):
        relayout(bad, data.particles)
