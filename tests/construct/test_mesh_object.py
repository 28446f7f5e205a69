"""mesh-to-object: a rigid spring-mass body from a closed mesh keeps its shape when dropped."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from twinbench.cli import main as cli
from twinbench.construct.mesh_object import mesh_particles, mesh_to_object
from twinbench.physics import ModelBuilder, SimParams, SpringMassSolver
from twinbench.twin import load_object


def test_particles_fill_the_mesh_and_the_body_stays_rigid():
    mesh = trimesh.creation.box(extents=(0.06, 0.04, 0.03))
    obj = mesh_to_object(mesh, name="box", spacing=0.01)
    p = obj.particles.astype(np.float64)
    assert np.all(np.abs(p) <= np.array([0.03, 0.02, 0.015]) + 1e-6)  # inside or on the box
    # interior lattice and surface points are both there
    assert np.any(np.all(np.abs(p) < [0.02, 0.01, 0.005], axis=1))
    assert np.sum(np.isclose(np.abs(p[:, 2]), 0.015)) > 4
    assert obj.binding == "rigid" and len(obj.gaussians) > 100
    b = ModelBuilder(SimParams(substeps=200, dt=1 / 30 / 200))
    b.add_body(p + [0, 0, 0.05], radius=obj.spring_radius, max_neighbors=obj.max_neighbors,
               spring_Y=obj.spring_Y)
    model = b.finalize("cpu")
    solver = SpringMassSolver(model)
    state, control = model.state(), model.control()
    for _ in range(12):
        solver.simulate_frame(state, control)
    x = state.x.numpy().astype(np.float64)
    assert x[:, 2].min() < 0.002  # it fell onto the ground
    s = model.springs_np[: model.num_object_springs]
    strain = np.linalg.norm(x[s[:, 0]] - x[s[:, 1]], axis=1) / model.rest_lengths_np[: len(s)] - 1
    assert np.abs(strain).max() < 0.05


def test_command_writes_an_object_directory(tmp_path):
    trimesh.creation.icosphere(subdivisions=2, radius=0.03).export(tmp_path / "ball.stl")
    assert cli(["mesh-to-object", str(tmp_path / "ball.stl"), "--spacing", "0.01", "--name", "ball",
                "--out", str(tmp_path / "ball")]) == 0
    obj, sim = load_object(tmp_path / "ball")
    assert obj.name == "ball" and obj.num_particles > 50 and sim == {}
    assert np.linalg.norm(obj.particles, axis=1).max() < 0.0301


def test_open_mesh_is_refused():
    mesh = trimesh.creation.box(extents=(0.05, 0.05, 0.05))
    mesh.update_faces(np.arange(len(mesh.faces) - 2))
    with pytest.raises(ValueError, match="not closed"):
        mesh_particles(mesh, 0.01)
