"""Particle masses by observed share (`sysid --masses observed`): a layout that samples the object unevenly
gets the masses of the volume each particle stands for, the same total, so its centre of mass is the
object's, not the crowded particles'."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from twinbench.cli import main as cli
from twinbench.construct.sysid_io import save_sysid_data
from twinbench.physics.model import lattice
from twinbench.physics.sysid_data import MASS_FLOOR, SysIdData, observed_masses


def _uneven_block(frames: int = 4, seed: int = 0, extra=None) -> SysIdData:
    """A 12 x 6 x 4 cm block at rest, seen as a 2 mm lattice (70 % of it visible per frame), whose particles
    lie 1 cm apart in its left half and 2 cm apart in its right half (8 times fewer per volume); `extra`
    particles (K, 3) after those."""
    rng = np.random.default_rng(seed)
    dense = lattice(60, 30, 20, 0.002, (-0.059, 0.001, 0.001))
    particles = np.concatenate([lattice(6, 6, 4, 0.01, (-0.055, 0.005, 0.005)),
                                lattice(3, 3, 2, 0.02, (0.01, 0.01, 0.01)), np.zeros((0, 3)) if extra is None
                                else extra])
    observed = np.repeat(dense[None], frames, 0) + rng.normal(0.0, 5e-4, (frames, *dense.shape))
    tracked_indices = np.arange(0, len(particles), 3)
    return SysIdData(particles, observed, rng.random((frames, len(dense))) < 0.7, tracked_indices,
                     np.repeat(particles[tracked_indices][None], frames, 0),
                     np.ones((frames, len(tracked_indices)), bool), np.zeros((frames, 0, 3)))


def test_observed_masses_give_each_particle_the_volume_it_stands_for():
    data = _uneven_block()
    m = observed_masses(data)
    assert m.sum() == pytest.approx(data.num_particles)
    assert m.min() >= MASS_FLOOR * m.mean() - 1e-12
    # away from where the halves meet, a 2 cm particle stands for 8 times the volume of a 1 cm one
    x = data.particles[:, 0]
    assert m[x > 0.02].mean() / m[x < -0.015].mean() == pytest.approx(8.0, rel=0.05)
    # the block's centre of mass is x = 0: unit masses put it 2.3 cm into the crowded half
    unit_x = data.particles[:, 0].mean()
    assert unit_x < -0.02
    assert abs(np.average(data.particles[:, 0], weights=m)) < 0.1 * abs(unit_x)


def test_a_particle_no_observed_point_reaches_keeps_the_floor_mass():
    # one particle 5 cm above the block: no observed point is near it, yet it may not go massless
    data = _uneven_block(extra=np.array([[0.0, 0.03, 0.09]]))
    m = observed_masses(data)
    assert m.sum() == pytest.approx(data.num_particles)
    assert m[-1] == pytest.approx(m.min())
    # lifted to the floor, then every mass scaled (by under 1) to keep the total
    assert 0.9 * MASS_FLOOR < m[-1] <= MASS_FLOOR


def test_observed_masses_refuse_data_they_cannot_weigh():
    data = _uneven_block()
    with pytest.raises(ValueError, match="interior completions"):
        observed_masses(replace(data, surface_indices=np.arange(10)))
    few = np.zeros_like(data.visibility)
    few[:, :5] = True
    with pytest.raises(ValueError, match="5 observed points visible in frame 0"):
        observed_masses(replace(data, visibility=few))


def test_sysid_cli_writes_the_observed_masses(tmp_path, capsys):
    data = _uneven_block()
    save_sysid_data(data, tmp_path / "case")
    args = ["sysid", "--data", str(tmp_path / "case"), "--no-progress", "--no-guess", "--no-stage1",
            "--no-stage2", "--no-stage3"]
    assert cli([*args, "--out-dir", str(tmp_path / "unit")]) == 0
    assert cli([*args, "--masses", "observed", "--out-dir", str(tmp_path / "observed")]) == 0
    assert "masses by observed share" in capsys.readouterr().err
    unit = np.load(tmp_path / "unit" / "object" / "object.npz")
    assert np.allclose(unit["masses"], 1.0)
    kept = np.load(tmp_path / "observed" / "object" / "object.npz")["masses"]
    assert kept == pytest.approx(observed_masses(data))
