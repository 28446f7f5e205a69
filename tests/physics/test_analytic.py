"""Known-answer checks of the integrator, springs, drag, ground contact and friction."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.physics import ModelBuilder, SimParams, SpringMassSolver
from twinbench.physics.model import lattice

G = 9.8


def _single(params: SimParams, x0, v0=(0.0, 0.0, 0.0)):
    b = ModelBuilder(params)
    b.add_body([x0], velocities=[v0])
    model = b.finalize()
    return model, SpringMassSolver(model), model.state(), model.control()


def test_free_fall_matches_parabola():
    p = SimParams(drag_damping=0.0, ground=False)
    model, solver, state, ctl = _single(p, (0.0, 0.0, 1.0))
    for _ in range(10):
        solver.simulate_frame(state, ctl)
    t = 10 * p.frame_dt
    z = float(state.x.numpy()[0, 2])
    # float32 recurrence of semi-implicit Euler (v += g dt; z += v dt), evaluated in numpy
    zf, vf, dt32, g32 = np.float32(1.0), np.float32(0.0), np.float32(p.dt), np.float32(-G)
    for _ in range(10 * p.substeps):
        vf = vf + g32 * dt32
        zf = zf + vf * dt32
    assert z == pytest.approx(float(zf), abs=1e-7)
    # the scheme lies g dt t / 2 = 8.2e-5 m below the parabola; float32 round-off adds ~2e-5 m here
    assert z == pytest.approx(1.0 - 0.5 * G * t * t, abs=0.5 * G * p.dt * t + 3e-5)
    assert float(state.v.numpy()[0, 2]) == pytest.approx(-G * t, rel=1e-3)


def test_drag_decays_speed_exponentially():
    p = SimParams(drag_damping=3.0, gravity=(0.0, 0.0, 0.0), ground=False)
    model, solver, state, ctl = _single(p, (0.0, 0.0, 1.0), v0=(2.0, 0.0, 0.0))
    for _ in range(15):
        solver.simulate_frame(state, ctl)
    t = 15 * p.frame_dt
    vx = float(state.v.numpy()[0, 0])
    # exactly the float32 drag factor applied once per substep ...
    factor = np.float64(np.exp(np.float32(-p.dt) * np.float32(3.0), dtype=np.float32))
    assert vx == pytest.approx(2.0 * factor ** (15 * p.substeps), rel=1e-5)
    # ... which is exp(-c t) up to the factor's float32 rounding (<= 3e-8 per substep)
    assert vx == pytest.approx(2.0 * np.exp(-3.0 * t), rel=5e-4)


def test_two_particle_spring_period():
    """Linear stiffness k = Y / L0, reduced mass m/2: T = 2 pi sqrt(m L0 / (2 Y))."""
    y, rest, m = 2000.0, 0.1, 1.0
    p = SimParams(drag_damping=0.0, dashpot_damping=0.0, gravity=(0.0, 0.0, 0.0), ground=False)
    b = ModelBuilder(p)
    b.add_body([[0.0, 0.0, 0.0], [0.102, 0.0, 0.0]], springs=[[0, 1]], rest_lengths=[rest], spring_Y=y,
               mass=m)
    model = b.finalize()
    solver = SpringMassSolver(model)
    a, c = model.state(), model.state()
    ctl = model.control()
    stretch = []
    for s in range(6000):  # 0.3 s, ~6 periods
        solver.step(a, c, ctl, substep_index=s % p.substeps)
        x = c.x.numpy()
        stretch.append(x[1, 0] - x[0, 0] - rest)
        a, c = c, a
    stretch = np.asarray(stretch)
    up = np.flatnonzero((stretch[:-1] < 0) & (stretch[1:] >= 0))
    # sub-sample crossing times by linear interpolation
    tc = (up + stretch[up] / (stretch[up] - stretch[up + 1])) * p.dt
    period = np.mean(np.diff(tc))
    expected = 2 * np.pi * np.sqrt((m / 2) * rest / y)
    assert period == pytest.approx(expected, rel=2e-3)
    assert np.abs(stretch).max() == pytest.approx(0.002, rel=1e-2)  # undamped: amplitude kept


@pytest.mark.parametrize("restitution", [0.0, 0.5])
def test_particle_resting_on_ground_does_not_sink_or_jitter(restitution):
    p = SimParams(ground_restitution=restitution)
    model, solver, state, ctl = _single(p, (0.1, 0.2, 0.0))
    zs = []
    for _ in range(30):
        solver.simulate_frame(state, ctl)
        zs.append(state.x.numpy()[0, 2])
    x, v = state.numpy()
    assert min(zs) >= 0.0
    assert max(zs) < 1e-7  # micro-hops of ~1e-8 m at e = 0.5, exactly 0 at e = 0
    assert np.abs(v).max() < 1e-3
    np.testing.assert_allclose(x[0, :2], [0.1, 0.2], atol=1e-7)
    if restitution == 0.0:
        assert max(zs) == 0.0


@pytest.mark.parametrize("mu", [0.3, 0.6])
def test_sliding_block_stops_at_coulomb_distance(mu):
    v0 = 0.5
    p = SimParams(drag_damping=0.0, ground_restitution=0.0, ground_friction=mu)
    pts = lattice(4, 3, 2)
    b = ModelBuilder(p)
    b.add_body(pts, velocities=np.tile([v0, 0.0, 0.0], (len(pts), 1)))
    model = b.finalize()
    solver = SpringMassSolver(model)
    state, ctl = model.state(), model.control()
    com0 = pts.mean(0)
    for _ in range(12):
        solver.simulate_frame(state, ctl)
    x, v = state.numpy()
    slide = x.mean(0)[0] - com0[0]
    assert np.abs(v).max() < 1e-2
    assert slide == pytest.approx(v0**2 / (2 * mu * G), rel=0.05)
    assert x[:, 2].min() >= -1e-7
