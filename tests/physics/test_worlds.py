"""Many worlds in one model: each world of an N-world model computes bit for bit what the same model built
with one world computes, and worlds never touch each other."""

from __future__ import annotations

import numpy as np
import pytest
import warp as wp
from scenes import pusher_scene as _builder
from scenes import run_pushed as _drive

from twinbench.physics import SpringMassSolver, check_divergence
from twinbench.physics import kernels as K


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_each_world_of_a_batch_is_bit_identical_to_the_same_run_alone(threads):
    """On one thread, or with groups of worlds on their own threads."""
    starts = [(0.0, 0.0, 0.0), (0.004, -0.01, 0.01), (-0.01, 0.02, 0.0)]
    speeds = [0.004, 0.006, 0.0]
    b, mid, nv = _builder()
    batch = b.finalize(num_worlds=3)
    assert batch.num_worlds == 3 and batch.num_particles == 3 * (27 + 18)
    assert batch.meshes_per_world == 2 and batch.control_points_per_world == 1
    pusher = batch.meshes[mid].vertices.astype(np.float64)
    mids = [mid + w * batch.meshes_per_world for w in range(3)]
    solver = SpringMassSolver(batch, threads=threads)
    assert solver._collide and solver.executor.name == ("threads" if threads > 1 else "one-core")
    assert len(getattr(solver.executor, "groups", [batch])) == threads
    got = _drive(batch, solver, batch.state(), batch.control(), mids, starts, pusher, 12, speeds)
    nw = batch.particles_per_world
    moved = np.abs(got[-1] - batch.x0_np).max()
    assert moved > 0.01  # the worlds fall, get pushed and collide: a real trajectory
    for w in range(3):
        b1, mid1, _ = _builder()
        alone = b1.finalize()
        solver1 = SpringMassSolver(alone)
        ref = _drive(alone, solver1, alone.state(), alone.control(), [mid1], [starts[w]],
                     pusher, 12, [speeds[w]])
        for f in range(12):
            assert np.array_equal(got[f][w * nw: (w + 1) * nw], ref[f]), (w, f)
        # each world's meshes felt only that world's particles
        for k in range(2):
            assert np.array_equal(solver.mesh_contact_force(k + w * 2), solver1.mesh_contact_force(k))
    assert np.abs(solver.mesh_contact_force(mids[1])).max() > 0  # a pusher really pushed


@pytest.mark.parametrize("collisions", [True, False])
def test_cpu_scatter_of_spring_forces_equals_the_per_particle_gather(collisions):
    """The CPU sums each spring into its ends in one pass; CUDA gathers per particle from per-spring forces.
    Both add in spring order: the gather path run on CPU gives the same trajectory and contact forces,
    bit for bit (three worlds, control springs, self-collision or none, static and moving meshes, the third
    world falling off the box onto the ground). Without collisions the scatter path's native finish (particles
    far from contacts moved outside Warp) meets the gather path's Warp loop; with them, the collision stage's
    native finish runs against its Warp loop (``_pending`` empty, as on CUDA)."""
    runs = []
    # (scatter, native finish); the scatter path's integration always lists its pending particles, so the
    # collision stage's Warp loop is the third reference only where there is a collision stage
    for scatter, native in ((True, True), (False, True), *([(True, False)] if collisions else [])):
        b, mid, _ = _builder(collisions)
        model = b.finalize(num_worlds=3)
        solver = SpringMassSolver(model, threads=1)
        assert solver._scatter and solver._collide == collisions
        solver._scatter = scatter
        if not native:
            solver._pending = wp.zeros(0, dtype=int, device=solver.device)
        pusher = model.meshes[mid].vertices.astype(np.float64)
        mids = [mid + w * model.meshes_per_world for w in range(3)]
        x = _drive(model, solver, model.state(), model.control(), mids,
                   [(0, 0, 0), (0.004, -0.01, 0.01), (0.25, 0.0, 0.0)], pusher, 8, [0.006, 0.004, 0.0])
        runs.append((x, [solver.mesh_contact_force(k, per_face=True) for k in range(6)]))
    nw = model.particles_per_world
    assert np.abs(runs[0][0][-1] - runs[0][0][0]).max() > 0.005
    assert runs[0][0][-1][2 * nw:, 2].min() < 0.01  # the third world reached the ground
    assert max(np.abs(f).max() for f in runs[0][1]) > 0  # and the meshes felt contacts
    for other in runs[1:]:
        for a, b in zip(runs[0][0] + runs[0][1], other[0] + other[1], strict=True):
            np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("listed", [False, True])
def test_cpu_spring_scatter_adds_each_springs_force_in_spring_order(listed):
    """The CPU scatter (batches of springs computed lane-wise) against the per-spring kernel of the gather
    path and a float32 sum in spring order: bit for bit, over several batches and a partial one, with runs of
    springs sharing their first end, unsorted ends, inactive springs (stiffness -1), a zero-length spring
    (direction clamped), a spring from a particle to itself, springs to the last particle (read from a padded
    copy) and, optionally, an index list read from an offset."""
    rng = np.random.default_rng(3)
    n, ns = 300, 1000
    first_ends = np.sort(rng.integers(0, n, ns))  # runs of springs sharing a first end, then random jumps
    second = rng.integers(0, n, ns)
    second[second == first_ends] = (second[second == first_ends] + 1) % n
    springs = np.stack([first_ends, second], 1).astype(np.int32)
    springs[100:140] = springs[100:140][::-1]  # not sorted
    springs[300] = springs[300, 0]  # a spring from a particle to itself
    springs[-3:, 0] = n - 1  # the last particle, whose 16-byte row would leave the array, as first end
    springs[[50, 51, 500], 1] = n - 1  # ... and as second end
    x = rng.normal(0, 0.05, (n, 3)).astype(np.float32)
    x[springs[7, 1]] = x[springs[7, 0]]  # a zero-length spring
    v = rng.normal(0, 0.2, (n, 3)).astype(np.float32)
    ry = np.stack([rng.uniform(0.01, 0.1, ns), rng.uniform(1e2, 1e5, ns)], 1).astype(np.float32)
    ry[rng.random(ns) < 0.1, 1] = -1.0  # inactive
    dev = "cpu"
    xs, vs = wp.array(x, dtype=wp.vec3, device=dev), wp.array(v, dtype=wp.vec3, device=dev)
    sp, rys = wp.array(springs, dtype=wp.vec2i, device=dev), wp.array(ry, dtype=wp.vec2, device=dev)
    per = wp.zeros(ns, dtype=wp.vec3, device=dev)
    none = wp.zeros(0, dtype=wp.vec3, device=dev)
    wp.launch(K.eval_spring_forces, dim=ns, inputs=[xs, vs, sp, rys, 3.0, none, none, 0.0, n], outputs=[per],
              device=dev)
    per = per.numpy()
    if listed:
        ids = np.sort(rng.choice(ns, 733, replace=False)).astype(np.int32)
        first, count, ids_wp = 5, 733 - 5, wp.array(ids, dtype=int, device=dev)
        order = ids[5:]
    else:
        first, count, ids_wp = 21, ns - 21, wp.zeros(0, dtype=int, device=dev)
        order = np.arange(21, ns)
    want = np.zeros((n, 3), np.float32)
    for s in order:
        a, b = springs[s]
        want[a] = want[a] + per[s]
        want[b] = want[b] - per[s]
    assert np.isfinite(per).all() and np.abs(per).max() > 0
    got = wp.zeros(n, dtype=wp.vec3, device=dev)
    wp.launch(K.scatter_object_springs, dim=1, inputs=[xs, vs, sp, rys, 3.0, first, count, ids_wp],
              outputs=[got], device=dev)
    np.testing.assert_array_equal(got.numpy(), want)


def test_a_diverging_world_leaves_the_others_untouched():
    b, mid, _ = _builder()
    batch = b.finalize(num_worlds=2)
    solver = SpringMassSolver(batch)
    state, ctl = batch.state(), batch.control()
    ref_state = batch.state()
    nw = batch.particles_per_world
    v = state.v.numpy()
    v[nw + 3] = np.nan  # world 1 blows up
    state.v.assign(v)
    for _ in range(5):
        solver.simulate_frame(state, ctl, check=False)
        solver.simulate_frame(ref_state, ctl, check=False)
    x = state.x.numpy()
    assert np.array_equal(x[:nw], ref_state.x.numpy()[:nw])  # world 0: as if world 1 were healthy
    bad = check_divergence(state)
    assert bad.size and bad.min() >= nw


def test_num_worlds_must_be_a_positive_integer():
    b, _, _ = _builder()
    with pytest.raises(ValueError, match="num_worlds"):
        b.finalize(num_worlds=0)


def test_mesh_boxes_only_skip_queries_that_find_nothing():
    """Particles outside a mesh's box (its vertices over the frame, grown past the margin) skip the mesh
    query: the same run with boxes that hold everything (every particle queried) is bit-identical, with
    particles pushed, resting on the box and sliding along the pusher's edges."""
    runs = []
    for pad in (None, 1e6):
        b, mid, _ = _builder()
        model = b.finalize()
        solver = SpringMassSolver(model, threads=1)
        if pad is not None:
            solver._pad = pad
            solver._cp.mesh_lo.fill_(-pad)
            solver._cp.mesh_hi.fill_(pad)
        pusher = model.meshes[mid].vertices.astype(np.float64)
        x = _drive(model, solver, model.state(), model.control(), [mid], [(0.0, 0.0, 0.0)], pusher, 12,
                   [0.006])
        runs.append((x, [solver.mesh_contact_force(k, per_face=True) for k in range(2)]))
    assert np.abs(runs[0][1][1]).max() > 0 and np.abs(runs[0][1][0]).max() > 0  # both meshes touched
    for a, b in zip(runs[0][0] + runs[0][1], runs[1][0] + runs[1][1], strict=True):
        np.testing.assert_array_equal(a, b)


def test_collision_candidates_of_overlapping_worlds_come_from_their_own_world():
    """One hash grid serves all worlds (points grouped by world): worlds placed on the same coordinates
    get exactly the candidate lists, in the same order, of the model built alone."""
    b, _, _ = _builder()
    alone = b.finalize()
    b3, _, _ = _builder()
    batch = b3.finalize(num_worlds=3)
    lists = []
    for model in (alone, batch):
        solver = SpringMassSolver(model, threads=1)
        state = model.state()
        x = state.x.numpy().reshape(model.num_worlds, -1, 3)
        x[:, 27:, 0] -= 0.06  # the second body against the first: particles of both come within range
        state.x.assign(x.reshape(-1, 3))
        solver.rebuild_collision_candidates(state)
        lists.append((solver.buffers.cand.numpy(), solver.buffers.cand_count.numpy()))
    (c1, n1), (c3, n3) = lists
    nw = alone.num_particles
    assert n1.sum() > 0
    for w in range(3):
        rows = slice(w * nw, (w + 1) * nw)
        np.testing.assert_array_equal(n3[rows], n1)
        for i in range(nw):
            np.testing.assert_array_equal(c3[w * nw + i, : n1[i]], c1[i, : n1[i]] + w * nw)
