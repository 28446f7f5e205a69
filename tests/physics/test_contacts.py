"""Contacts with static/kinematic triangle meshes and between bodies; determinism."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from twinbench.physics import ModelBuilder, SimParams, SpringMassSolver
from twinbench.physics.model import lattice

G = 9.8


def test_soft_cube_rests_on_static_box_and_box_carries_its_weight():
    p = SimParams(ground_restitution=0.0, ground_friction=0.5)
    b = ModelBuilder(p)
    b.add_body(lattice(5, 5, 5, origin=(-0.02, -0.02, 0.15)))
    box = trimesh.creation.box(extents=(0.2, 0.2, 0.1))
    box.apply_translation((0.0, 0.0, 0.05))  # top face at z = 0.1
    mid = b.add_static_mesh(box.vertices, box.faces, restitution=0.0, friction=0.5)
    model = b.finalize()
    solver = SpringMassSolver(model)
    state, ctl = model.state(), model.control()
    for _ in range(30):  # 1 s: falls 5 cm, lands, settles
        solver.simulate_frame(state, ctl)
    x, v = state.numpy()
    top = 0.1
    # resting on top, kept at the contact margin (5 mm), not sunk and not on the ground
    assert x[:, 2].min() > top
    assert x[:, 2].min() < top + p.mesh_margin + 1e-3
    assert np.abs(v).max() < 1e-3
    np.testing.assert_allclose(x.mean(0)[:2], 0.0, atol=1e-3)
    # the box carries the full weight: mean contact force = sum(m) g upward (125 kg of unit masses)
    f = solver.mesh_contact_force(mid)
    assert abs(f[2] - 125 * G) < 0.01 * 125 * G
    assert np.abs(f[:2]).max() < 1.0
    per_face = solver.mesh_contact_force(mid, per_face=True)
    assert per_face.shape == (12, 3)
    np.testing.assert_allclose(per_face.sum(0), f, rtol=1e-4, atol=1e-2)  # float32 sums, other order


def test_fingers_latch_and_lift_cube_by_friction():
    """Two kinematic fingers close on a cube, latch at a force threshold, lift it 5 cm and hold 1 s."""
    p = SimParams(ground_restitution=0.0, ground_friction=0.5)
    b = ModelBuilder(p)
    cube = lattice(5, 5, 5, origin=(-0.02, -0.02, 0.0))
    b.add_body(cube)
    finger = trimesh.creation.box(extents=(0.01, 0.04, 0.04))
    verts = [np.asarray(finger.vertices) + (s * 0.035, 0.0, 0.02) for s in (-1, 1)]
    ids = [b.add_kinematic_mesh(v, finger.faces, restitution=0.0, friction=1.0) for v in verts]
    model = b.finalize()
    solver = SpringMassSolver(model)
    state, ctl = model.state(), model.control()
    fdt = p.frame_dt
    threshold, close_speed, lift_speed, lift_height = 2000.0, 0.05, 0.1, 0.05
    latched_at, lift_frames = None, int(round(lift_height / (lift_speed * fdt)))
    hold_frames = int(np.ceil(1.0 / fdt))
    k = 0
    while latched_at is None or k <= latched_at + lift_frames + hold_frames:
        step = np.zeros(3)
        if latched_at is None:
            nxt = [verts[0] + (close_speed * fdt, 0, 0), verts[1] - (close_speed * fdt, 0, 0)]
        else:
            if k - latched_at <= lift_frames:
                step[2] = lift_speed * fdt
            nxt = [verts[0] + step, verts[1] + step]
        for mid, a, c in zip(ids, verts, nxt, strict=True):
            ctl.set_kinematic_mesh(mid, a, c)
        solver.simulate_frame(state, ctl)
        verts = nxt
        forces = [solver.mesh_contact_force(mid) for mid in ids]
        if latched_at is None and forces[0][0] > threshold and forces[1][0] < -threshold:
            latched_at = k  # each finger pushes the cube inward (left +x, right -x)
        k += 1
        if latched_at is None:
            assert k < 10, "fingers never reached the latch threshold"
    x, v = state.numpy()
    assert verts[0][:, 2].min() > lift_height - 1e-6  # finger bottoms lifted from z = 0
    # cube carried up with the fingers (COM rose by the lift height, within 5 mm), at rest, held 1 s
    assert x[:, 2].mean() - cube[:, 2].mean() > lift_height - 0.005
    assert x[:, 2].min() > lift_height - 0.005
    assert np.abs(v).max() < 1e-2
    # friction carries the weight: vertical contact forces of both fingers sum to m g
    fz = sum(solver.mesh_contact_force(mid)[2] for mid in ids)
    assert abs(fz - len(cube) * G) < 0.02 * len(cube) * G


def _two_cubes(candidate_radius_scale: float = 2.0, self_collision: bool = False):
    p = SimParams(ground_restitution=0.0, ground_friction=0.5, collision_dist=0.02, object_restitution=0.0,
                  object_friction=0.5, candidate_radius_scale=candidate_radius_scale,
                  self_collision=self_collision)
    b = ModelBuilder(p)
    b.add_body(lattice(4, 4, 4))  # resting on the ground, top at z = 0.03
    b.add_body(lattice(4, 4, 4, origin=(0.0, 0.0, 0.08)))  # 5 cm gap above it
    model = b.finalize()
    return model, SpringMassSolver(model)


@pytest.mark.parametrize("self_collision", [False, True])
def test_dropped_cubes_do_not_interpenetrate(self_collision):
    """Body-body contact (masks = body ids) and self-collision (every particle its own mask, spring
    neighbours excluded) both keep the upper cube above the lower one."""
    model, solver = _two_cubes(self_collision=self_collision)
    state, ctl = model.state(), model.control()
    cd = model.params.collision_dist
    for _ in range(45):
        solver.simulate_frame(state, ctl)
        x = state.x.numpy()
        a, b = x[:64], x[64:]
        dmin = np.linalg.norm(a[:, None] - b[None], axis=-1).min()
        assert dmin > 0.5 * cd
        assert b[:, 2].min() > a[:, 2].max() + 0.5 * cd
    x, v = state.numpy()
    assert np.abs(v).max() < 5e-3  # settled on top
    np.testing.assert_allclose(x[64:, :2].mean(0), x[:64, :2].mean(0), atol=2e-3)


def test_spring_neighbours_never_collide_with_self_collision_on():
    """A single resting body with self-collision: every close pair is a spring, so nothing happens."""
    p = SimParams(self_collision=True, collision_dist=0.015, ground_restitution=0.0)
    b = ModelBuilder(p)
    b.add_body(lattice(3, 3, 3))
    model = b.finalize()
    solver = SpringMassSolver(model)
    solver.rebuild_collision_candidates(model.state())
    assert int(solver.buffers.cand_count.numpy().sum()) == 0
    # without springs the same close pairs are candidates
    b2 = ModelBuilder(p)
    b2.add_body(lattice(3, 3, 3), springs=np.zeros((0, 2), np.int32))
    model2 = b2.finalize()
    solver2 = SpringMassSolver(model2)
    solver2.rebuild_collision_candidates(model2.state())
    assert int(solver2.buffers.cand_count.numpy().sum()) > 0


def test_runs_are_bitwise_identical():
    runs = []
    for _ in range(2):
        model, solver = _two_cubes()
        state, ctl = model.state(), model.control()
        for _ in range(6):
            solver.simulate_frame(state, ctl)
        runs.append(np.concatenate(state.numpy()))
    assert np.array_equal(runs[0], runs[1])


def test_candidate_lists_equal_phystwins_full_radius_lookup_in_the_same_order():
    """The solver looks up only the hash cells within (1.25x) the candidate radius; PhysTwin queries the
    5 * collision_dist cell radius. Same lists, same order (the impulses are summed in list order), for a
    jittered dense body with self-collision and a candidate cap that cuts lists short."""
    import warp as wp

    from twinbench.physics import kernels as K

    rng = np.random.default_rng(3)
    pts = lattice(8, 8, 8, spacing=0.01) + rng.normal(0.0, 0.002, (512, 3))
    p = SimParams(self_collision=True, collision_dist=0.021, max_collision_candidates=20)
    b = ModelBuilder(p)
    b.add_body(pts, springs=np.zeros((0, 2), np.int32))
    model = b.finalize()
    solver = SpringMassSolver(model)
    state = model.state()
    solver.rebuild_collision_candidates(state)
    ours = solver.buffers.cand.numpy().copy(), solver.buffers.cand_count.numpy().copy()
    cell = 5.0 * p.collision_dist
    grid = wp.HashGrid(64, 64, 64, device="cpu")
    grid.build(state.x, cell, groups=model.particle_world)
    cand, count = wp.zeros_like(solver.buffers.cand), wp.zeros_like(solver.buffers.cand_count)
    inputs = [grid.id, state.x, model.masks, model.particle_world, model.nbr_offsets, model.nbr,
              p.collision_dist, cell, 0, 0]
    wp.launch(K.build_candidates, dim=512, inputs=inputs, outputs=[cand, count], device="cpu")
    assert ours[1].sum() > 5000 and (ours[1] == 20).any()  # many candidates, some lists capped
    np.testing.assert_array_equal(ours[1], count.numpy())
    for i in range(512):
        np.testing.assert_array_equal(ours[0][i, :ours[1][i]], cand.numpy()[i, :ours[1][i]])
