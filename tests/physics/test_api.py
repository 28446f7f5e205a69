"""Differentiability, divergence reporting and input validation."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp

from twinbench.physics import (
    ModelBuilder,
    SimParams,
    SimulationDiverged,
    SpringMassSolver,
    State,
    check_device,
    check_divergence,
)
from twinbench.physics.model import lattice


@wp.kernel
def _weighted_displacement(x: wp.array(dtype=wp.vec3), x0: wp.array(dtype=wp.vec3),
                           w: wp.array(dtype=wp.vec3), out: wp.array(dtype=float)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.dot(w[i], x[i] - x0[i]))


def test_tape_gradient_wrt_log_stiffness_matches_finite_differences():
    """300 substeps of a soft 3x3x2 block with random velocities, two moving control points and
    ground contact; loss = w . (x - x0). Central differences in float64 log Y steps of 1e-2 / 3e-2
    (large enough to dominate the float32 round-off of the loss, small enough for O(h^2) < 0.1 %)."""
    rng = np.random.default_rng(0)
    pts = lattice(3, 3, 2)
    b = ModelBuilder(SimParams(ground_restitution=0.0))
    b.add_body(pts, velocities=rng.normal(0.0, 0.5, (len(pts), 3)), spring_Y=3e3)
    b.add_control_points([[-0.005, 0.0, 0.0], [-0.005, 0.02, 0.01]], radius=0.02, max_neighbors=5)
    model = b.finalize(requires_grad=True)
    solver = SpringMassSolver(model)
    ctl = model.control()
    c0 = model.control_x0_np
    ctl.set_control_points(c0, c0 + [0.0, 0.0, 0.01])
    w = wp.array(rng.normal(size=(len(pts), 3)), dtype=wp.vec3)
    x0 = wp.array(pts, dtype=wp.vec3)

    def loss(log_y):
        model.set_spring_log_y(log_y)
        states = [model.state() for _ in range(301)]
        out = wp.zeros(1, dtype=float, requires_grad=True)
        for s in range(300):
            solver.step(states[s], states[s + 1], ctl, substep_index=s)
        wp.launch(_weighted_displacement, dim=len(pts), inputs=[states[-1].x, x0, w], outputs=[out])
        return out

    base = model.log_y_np.copy()
    tape = wp.Tape()
    with tape:
        out = loss(base)
    tape.backward(out)
    grad = model.log_y.grad.numpy().astype(np.float64)
    assert np.all(np.isfinite(grad)) and np.abs(grad).max() > 0

    def central(direction, h):
        lp = float(loss((base + h * direction).astype(np.float32)).numpy()[0])
        lm = float(loss((base - h * direction).astype(np.float32)).numpy()[0])
        return (lp - lm) / (2 * h)

    d = rng.normal(size=base.shape)
    assert grad @ d == pytest.approx(central(d, 1e-2), rel=1e-2)
    for s in np.argsort(-np.abs(grad))[:3]:  # the three most influential springs
        e = np.zeros_like(base, dtype=np.float64)
        e[s] = 1.0
        assert grad[s] == pytest.approx(central(e, 3e-2), rel=1e-2)


def test_divergence_is_reported_with_particle_indices():
    p = SimParams(ground=False, gravity=(0.0, 0.0, 0.0), dashpot_damping=0.0, drag_damping=0.0,
                  dt=1e-3, substeps=10)
    b = ModelBuilder(p)
    # a very stiff spring stretched 50 %, explicit Euler at dt = 1e-3 blows up
    b.add_body([[0, 0, 0], [0.015, 0, 0], [1.0, 1.0, 1.0]], springs=[[0, 1]], rest_lengths=[0.01],
               spring_Y=1e5)
    model = b.finalize()
    solver = SpringMassSolver(model)
    state, ctl = model.state(), model.control()
    assert check_divergence(state).size == 0
    with pytest.raises(SimulationDiverged) as err:
        for _ in range(50):
            solver.simulate_frame(state, ctl)
    assert set(err.value.indices.tolist()) == {0, 1}  # particle 2 has no spring and stays put
    assert set(check_divergence(state).tolist()) == {0, 1}


def test_state_and_control_are_separate_objects():
    b = ModelBuilder(SimParams())
    b.add_body(lattice(2, 2, 2, origin=(0, 0, 0.1)))
    model = b.finalize()
    solver = SpringMassSolver(model)
    s1, s2, ctl = model.state(), model.state(), model.control()
    solver.simulate_frame(s1, ctl)
    np.testing.assert_array_equal(s2.x.numpy(), model.x0_np)  # untouched
    assert s1.x.numpy()[:, 2].max() < 0.11


@pytest.mark.parametrize(
    ("call", "name"),
    [
        (lambda b: b.add_body(np.zeros((0, 3))), "points"),
        (lambda b: b.add_body(np.zeros((4, 2))), "points"),
        (lambda b: b.add_body([[0, 0, np.nan], [0, 0, 0.01]]), "points"),
        (lambda b: b.add_body(lattice(2, 2, 2), radius=-0.1), "radius"),
        (lambda b: b.add_body(lattice(2, 2, 2), max_neighbors=0), "max_neighbors"),
        (lambda b: b.add_body(lattice(2, 2, 2), mass=np.ones(3)), "mass"),
        (lambda b: b.add_body(lattice(2, 2, 2), spring_Y=-1.0), "spring_Y"),
        (lambda b: b.add_body(lattice(2, 2, 2), springs=[[0, 9]]), "springs"),
        (lambda b: b.add_body(lattice(2, 2, 2), velocities=np.zeros((3, 3))), "velocities"),
        (lambda b: b.add_control_points([[0, 0, 0]]), "add bodies"),
        (lambda b: b.add_static_mesh(np.zeros((3, 3)), [[0, 1, 5]]), "faces"),
        (lambda b: b.add_static_mesh(np.zeros((3, 3)), [[0, 1, 2]], restitution=2.0), "restitution"),
        (lambda b: b.finalize(), "add_body"),
    ],
)
def test_bad_builder_input_names_the_argument(call, name):
    with pytest.raises(ValueError, match=name):
        call(ModelBuilder(SimParams()))


def test_a_device_warp_cannot_run_on_is_refused_naming_the_field_and_the_fix():
    from twinbench.errors import InputError

    assert check_device("cpu") == "cpu"
    for bad in ("gpu", "cuda:x", "CPU", "cuda:"):
        with pytest.raises(InputError, match=rf"--device '{bad}': expected 'cpu', 'cuda' or 'cuda:N'"):
            check_device(bad, "--device")
    count = wp.get_cuda_device_count()
    with pytest.raises(InputError, match=f"{count} CUDA device" if count else "no CUDA device"):
        check_device(f"cuda:{count + 7}")
    b = ModelBuilder(SimParams())
    b.add_body(lattice(2, 2, 2))
    with pytest.raises(InputError, match="device 'cuda:"):  # before any array is made (Warp's own error is
        b.finalize(f"cuda:{count + 7}")                      # a RuntimeError from inside a launch)
    if count == 0:
        with pytest.raises(InputError, match="use 'cpu'"):
            check_device("cuda")


def test_bad_control_input_names_the_argument():
    b = ModelBuilder(SimParams())
    b.add_body(lattice(2, 2, 2))
    b.add_control_points([[-0.005, 0.0, 0.0]], radius=0.02)
    mesh = b.add_kinematic_mesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]],
                                [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    model = b.finalize()
    ctl = model.control()
    with pytest.raises(ValueError, match="frm"):
        ctl.set_control_points(np.zeros((2, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="to"):
        ctl.set_control_points(np.zeros((1, 3)), np.full((1, 3), np.nan))
    with pytest.raises(ValueError, match="vertices_to"):
        ctl.set_kinematic_mesh(mesh, np.zeros((4, 3)), np.zeros((5, 3)))
    with pytest.raises(ValueError, match="mesh_id"):
        ctl.set_kinematic_mesh(mesh + 1, np.zeros((4, 3)), np.zeros((4, 3)))
    with pytest.raises(ValueError, match="dt"):
        SimParams(dt=-1.0)
    with pytest.raises(ValueError, match="log_y"):
        model.set_spring_log_y(np.zeros(3))


@pytest.mark.parametrize("with_mesh", [False, True])
def test_new_stiffness_reaches_the_cached_frame(with_mesh):
    """set_spring_log_y between frames is honoured by the captured graph / recorded launches."""

    def build():
        b = ModelBuilder(SimParams())
        b.add_body(lattice(3, 2, 2, origin=(0.0, 0.0, 0.02)), spring_Y=1e3)
        if with_mesh:
            b.add_kinematic_mesh([[0.5, 0, 0], [0.6, 0, 0], [0.5, 0.1, 0], [0.5, 0, 0.1]],
                                 [[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        m = b.finalize()
        return m, SpringMassSolver(m)

    m1, s1 = build()
    st1, c1 = m1.state(), m1.control()
    s1.simulate_frame(st1, c1)
    new = np.full(m1.num_springs, np.log(3e4), np.float32)
    m1.set_spring_log_y(new)
    s1.simulate_frame(st1, c1)

    m2, s2 = build()
    st2, c2 = m2.state(), m2.control()
    s2.simulate_frame(st2, c2)
    before = st2.x.numpy().copy()
    m2.set_spring_log_y(new)
    ref = SpringMassSolver(m2)  # fresh solver: nothing cached
    ref.simulate_frame(st2, c2)
    np.testing.assert_array_equal(st1.x.numpy(), st2.x.numpy())
    assert not np.array_equal(before, st2.x.numpy())


@wp.kernel
def _axpy(a: float, x: wp.array(dtype=wp.vec3), y: wp.array(dtype=wp.vec3), out: wp.array(dtype=wp.vec3)):
    i = wp.tid()
    out[i] = a * x[i] + y[i]


def test_a_replayable_cpu_launch_calls_the_kernel_directly_with_the_recorded_arguments():
    """Recorded frames replay their launches through `replayable`: a direct call of the compiled kernel
    (with the pinned Warp) that computes what the recorded launch computes, call after call."""
    from twinbench.physics.frames import replayable

    rng = np.random.default_rng(1)
    x, y = (wp.array(rng.normal(size=(50, 3)), dtype=wp.vec3, device="cpu") for _ in range(2))
    out = wp.zeros(50, dtype=wp.vec3, device="cpu")
    launch = wp.launch(_axpy, dim=50, inputs=[2.5, x, y], outputs=[out], device="cpu", record_cmd=True)
    run = replayable(launch)
    assert run != launch.launch  # the direct path, not Warp's per-call packing
    expected = np.float32(2.5) * x.numpy() + y.numpy()
    out.zero_()
    run()
    np.testing.assert_array_equal(out.numpy(), expected)
    x.assign(np.ones((50, 3)))  # same arrays, new contents: a replay reads them now
    run()
    np.testing.assert_array_equal(out.numpy(), np.float32(2.5) + y.numpy())

    class Unlike:  # a launch object of another layout: Warp's own replay
        device = wp.get_device("cpu")
        launch = "launch.launch"

    assert replayable(Unlike()) == "launch.launch"


def test_a_new_time_step_inside_a_cpu_graph_capture_is_refused_with_the_fix():
    """The CPU integration reads a drag factor computed once per (dt, drag) by a launch, which a capture
    would only record: the model's own dt is ready from the start, a new one must first run uncaptured."""
    b = ModelBuilder(SimParams())
    b.add_body(lattice(2, 2, 2, origin=(0.0, 0.0, 0.1)))
    model = b.finalize()
    solver = SpringMassSolver(model)
    a, c, ctl = model.state(), model.state(), model.control()
    with wp.ScopedCapture(device="cpu"):
        solver.step(a, c, ctl)  # the model's dt: fine
    with pytest.raises(RuntimeError, match="outside a graph capture"), wp.ScopedCapture(device="cpu"):
        solver.step(a, c, ctl, dt=1e-5)
    solver.step(a, c, ctl, dt=1e-5)  # uncaptured: computes it
    with wp.ScopedCapture(device="cpu"):
        solver.step(a, c, ctl, dt=1e-5)


def test_step_refuses_strided_state_arrays_on_cpu():
    """The CPU spring pass reads particles through raw element pointers: a strided view is refused by name."""
    b = ModelBuilder(SimParams())
    b.add_body(lattice(2, 2, 2, origin=(0.0, 0.0, 0.1)))
    model = b.finalize()
    solver = SpringMassSolver(model)
    n = model.num_particles
    wide = wp.zeros(2 * n, dtype=wp.vec3, device="cpu")
    strided = State(x=wide[::2], v=wp.zeros(n, dtype=wp.vec3, device="cpu"))
    assert not strided.x.is_contiguous
    with pytest.raises(ValueError, match=r"state_in\.x and state_in\.v must be contiguous"):
        solver.step(strided, model.state(), model.control())
    solver.step(model.state(), model.state(), model.control())
