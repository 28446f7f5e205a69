"""One world on two CPU cores: frames split with a helper process are bit-identical to frames on one core,
contact forces included, and a helper that dies leaves the run on one core with the same results."""

from __future__ import annotations

import os
import signal
import time

import numpy as np
import pytest
import trimesh
from scenes import pusher_scene as _builder
from scenes import run_pushed as _drive

from twinbench.physics import ModelBuilder, SimParams, SpringMassSolver
from twinbench.physics import split as S
from twinbench.physics.model import lattice

pytestmark = pytest.mark.skipif(not S.split_supported(), reason="split frames need x86-64")


@pytest.fixture(autouse=True)
def _split_small_models_and_stay_split(monkeypatch):
    monkeypatch.setattr(S, "SPLIT_MIN_WORK", 0)  # split even these small models
    monkeypatch.setattr(S, "CONTENDED_FRAMES", 10**9)  # a busy CI machine must not end the split


def _run(threads: int, frames: int = 10, kill_after: int | None = None, collisions: bool = True,
         stop_after: int | None = None):
    b, mid, _ = _builder(collisions)
    model = b.finalize()
    solver = SpringMassSolver(model, threads=threads)
    pusher = model.meshes[mid].vertices.astype(np.float64)
    state, ctl = model.state(), model.control()
    out, forces = [], []
    for f in range(frames):
        out += _drive(model, solver, state, ctl, [mid], [(0.0, 0.0, 0.0)] if f == 0 else [(0, 0, 0)],
                      pusher + [0.006 * f, 0, 0], 1, [0.006])
        forces.append([solver.mesh_contact_force(k, per_face=True) for k in range(2)])
        if kill_after is not None and f == kill_after:
            assert solver.executor.name == "split"
            solver.executor.proc.kill()
            solver.executor.proc.wait()
        if stop_after is not None and f == stop_after:
            assert solver.executor.name == "split"
            stopped = solver.executor.proc
            os.kill(stopped.pid, signal.SIGSTOP)  # alive but never running again
    split_used = solver.executor.name == "split"
    solver.close()
    if stop_after is not None:
        assert stopped.poll() is not None  # the stopped helper was killed, not left behind
    return out, forces, split_used


def test_split_frames_are_bit_identical_to_one_core():
    one, f1, used1 = _run(1)
    two, f2, used2 = _run(2)
    assert not used1 and used2
    assert np.abs(one[-1] - one[0]).max() > 0.01  # falling, pushed, colliding: a real trajectory
    for a, b in zip(one, two, strict=True):
        assert np.array_equal(a, b)
    for a, b in zip(f1, f2, strict=True):
        for x, y in zip(a, b, strict=True):
            assert np.array_equal(x, y)
    assert max(np.abs(f[1]).max() for f in f1) > 0  # the pusher pushed


def test_a_dead_helper_falls_back_to_one_core_with_the_same_results():
    one, f1, _ = _run(1)
    with pytest.warns(UserWarning, match="one core"):
        two, f2, used = _run(2, kill_after=3)
    assert not used
    for a, b in zip(one, two, strict=True):
        assert np.array_equal(a, b)


def test_a_stopped_helper_is_detected_and_the_run_falls_back_with_the_same_results(monkeypatch):
    monkeypatch.setattr(S, "STALL_TIMEOUT_S", 1.0)  # max(10 s, 50 frames) by default: a quick test here
    monkeypatch.setattr(S, "STALL_FRAMES", 2)
    one, f1, _ = _run(1)
    with pytest.warns(UserWarning, match="one core.*stalled"):
        two, f2, used = _run(2, stop_after=3)
    assert not used
    for a, b in zip(one, two, strict=True):
        assert np.array_equal(a, b)
    for a, b in zip(f1, f2, strict=True):
        for x, y in zip(a, b, strict=True):
            assert np.array_equal(x, y)


def test_small_models_and_many_worlds_do_not_split(monkeypatch):
    monkeypatch.setattr(S, "SPLIT_MIN_WORK", 8000)
    b, _, _ = _builder()
    assert not S.wants_split(b.finalize(), 2)  # too little work per substep
    b, _, _ = _builder()
    assert not S.wants_split(b.finalize(num_worlds=2), 2)  # worlds use threads instead


def test_a_twin_env_on_two_cores_matches_one_core(monkeypatch):
    """Rope routing (gripper latch, clip collider): the env's own solver splits its frames."""
    from twinbench.env import TwinEnv

    runs = []
    for cores in ("1", "2"):
        monkeypatch.setenv("TWINBENCH_CPU_THREADS", cores)
        env = TwinEnv("rope-routing", preset="fast")
        obs, _ = env.reset(options={"init_state": 4})
        a = obs["agent_pos"].astype(np.float64)
        frames = []
        for k in range(8):
            a[2] -= 0.01
            a[7] = 1.0 if k >= 5 else 0.0
            obs, _, _, _, info = env.step(a)
            frames.append((obs["pixels"]["front"], env.twin.particles(env.state, "rope"), info["grasp"]))
        runs.append(frames)
        assert (env.twin.solver.executor.name == "split") == (cores == "2")
        env.twin.solver.close()
    for (p1, x1, g1), (p2, x2, g2) in zip(*runs, strict=True):
        assert np.array_equal(p1, p2) and np.array_equal(x1, x2) and g1 == g2


def test_contact_forces_are_exact_when_the_main_process_is_preempted_after_a_barrier(monkeypatch):
    """The main side sums the per-particle mesh contact forces after each substep's barrier, while the helper
    already runs the next substep: a main process descheduled there must still read this substep's forces."""
    one, f1, _ = _run(1, collisions=False)  # no particle contacts: one barrier per substep
    barrier = S._Barrier.__call__

    def preempted(self):
        barrier(self)
        time.sleep(0.0005)  # the helper runs on meanwhile (this patch lives in the main process only)

    monkeypatch.setattr(S._Barrier, "__call__", preempted)
    two, f2, used = _run(2, collisions=False)
    assert used
    for a, b in zip(one, two, strict=False):
        assert np.array_equal(a, b)
    assert max(np.abs(f[1]).max() for f in f2) > 0  # the pusher touched within these frames
    for a, b in zip(f1, f2, strict=False):
        for x, y in zip(a, b, strict=True):
            assert np.array_equal(x, y)


def test_spring_runs_cover_the_ids_in_order_with_long_runs_as_ranges():
    ids = np.r_[3, 7, 8, 10:600, 601, 605, 700:1000, 1002].astype(np.int32)
    runs = S._spring_runs(ids, False, "cpu", min_run=256)
    got = np.concatenate([np.arange(first, first + count) if listed is None else listed.numpy()
                          for _, first, count, listed in runs])
    assert np.array_equal(got, ids)
    assert [(first, count) for _, first, count, listed in runs if listed is None] == [(10, 590), (700, 300)]
    assert len(runs) == 5 and S._spring_runs(np.zeros(0, np.int32), True, "cpu") == []


def test_contacts_of_both_halves_with_one_mesh_are_summed_in_particle_order():
    """A tilted block landing across a static box: both halves touch the same mesh in the same substeps, with
    different forces, so the split's per-side contact lists must be added main side first, as one core
    adds them in particle order."""
    forces = []
    for threads in (1, 2):
        b = ModelBuilder(SimParams(ground_friction=0.6))
        pts = lattice(8, 3, 3, origin=(-0.04, -0.01, 0.105))
        pts[:, 2] += 0.05 * (pts[:, 0] + 0.04)  # one end lower: contacts start at different times
        b.add_body(pts, spring_Y=1e4)
        box = trimesh.creation.box(extents=(0.3, 0.3, 0.1))
        box.apply_translation((0.0, 0.0, 0.05))
        b.add_static_mesh(box.vertices, box.faces, friction=0.4)
        model = b.finalize()
        solver = SpringMassSolver(model, threads=threads)
        state, ctl = model.state(), model.control()
        run = []
        for _ in range(8):
            solver.simulate_frame(state, ctl)
            run.append(solver.mesh_contact_force(0, per_face=True))
        assert (solver.executor.name == "split") == (threads == 2)
        z, half = state.x.numpy()[:, 2], model.num_particles // 2
        assert z[:half].min() < 0.11 and z[half:].min() < 0.11  # both halves lie on the box (top at 0.1)
        solver.close()
        forces.append(run)
    assert max(np.abs(f).max() for f in forces[0]) > 0
    for a, b in zip(*forces, strict=True):
        assert np.array_equal(a, b)
