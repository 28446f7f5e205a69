"""A scene shared by the many-world and split-frame tests: two bodies with self-collision, a control point,
a static box and a kinematic pusher."""

from __future__ import annotations

import numpy as np
import trimesh

from twinbench.physics import ModelBuilder, SimParams
from twinbench.physics.model import lattice


def pusher_scene(collisions: bool = True) -> tuple[ModelBuilder, int, int]:
    """Two bodies (with self- and object collision unless told), control points, a static box and a kinematic
    pusher."""
    p = SimParams(self_collision=collisions, object_collision=collisions, ground_friction=0.6)
    b = ModelBuilder(p)
    b.add_body(lattice(3, 3, 3, origin=(-0.05, 0.0, 0.12)), spring_Y=2e4)
    b.add_body(lattice(3, 3, 2, origin=(0.02, 0.0, 0.12)), spring_Y=5e3)
    b.add_control_points([[-0.05, 0.0, 0.16]], radius=0.03)
    box = trimesh.creation.box(extents=(0.3, 0.3, 0.1))
    box.apply_translation((0.0, 0.0, 0.05))
    b.add_static_mesh(box.vertices, box.faces, friction=0.4)
    pusher = trimesh.creation.box(extents=(0.02, 0.06, 0.06))
    pusher.apply_translation((-0.1, 0.01, 0.13))
    mid = b.add_kinematic_mesh(pusher.vertices, pusher.faces, friction=0.8)
    return b, mid, pusher.vertices.shape[0]


def run_pushed(model, solver, state, ctl, mids, starts, pusher, frames: int, speeds) -> list[np.ndarray]:
    """Each world w: its objects shifted by starts[w], its pusher moving along +x at speeds[w]."""
    nw = model.particles_per_world
    x = state.x.numpy()
    for w, off in enumerate(starts):
        x[w * nw: (w + 1) * nw] += np.asarray(off, np.float32)
    state.x.assign(x)
    out = []
    for f in range(frames):
        for mid, speed in zip(mids, speeds, strict=True):
            ctl.set_kinematic_mesh(mid, pusher + [speed * f, 0, 0], pusher + [speed * (f + 1), 0, 0])
        ctl.set_control_points(np.tile([[-0.05, 0.0, 0.16]], (len(mids), 1)) + [0, 0, 0.001 * f],
                               np.tile([[-0.05, 0.0, 0.16]], (len(mids), 1)) + [0, 0, 0.001 * (f + 1)])
        solver.simulate_frame(state, ctl)
        out.append(state.x.numpy().copy())
    return out
