"""twinbench.physics: PhysTwin-compatible spring-mass simulation in NVIDIA Warp (CPU and CUDA).

    params = SimParams(ground_friction=0.5)              # frozen, DESIGN section 4 defaults
    b = ModelBuilder(params)
    body = b.add_body(points, radius=0.02, max_neighbors=30, spring_Y=3e4, mass=1.0)
    ctrl = b.add_control_points(handles, radius=0.04, max_neighbors=50)     # -> slice
    box = b.add_static_mesh(vertices, faces, restitution=0.0, friction=0.5)  # -> mesh id
    finger = b.add_kinematic_mesh(vertices, faces, restitution=0.0, friction=1.0)
    model = b.finalize("cpu")                            # or "cuda:0"; requires_grad=True for wp.Tape
    solver = SpringMassSolver(model)
    state, control = model.state(), model.control()
    control.set_control_points(frm, to); control.set_kinematic_mesh(finger, v_from, v_to)
    solver.simulate_frame(state, control)                # 667 substeps, in place, graph replay
    solver.executor.name    # who runs frames: "one-core" | "threads" (worlds) | "split" (physics.frames)
    solver.mesh_contact_force(finger)                    # mean force on the particles, N
    solver.step(state_in, state_out, control, substep_index=s)   # one substep
    solver.simulate_frame_tape(state, control)           # taped frame, one State per substep

The golden PhysTwin trajectories are reproduced bitwise on CPU (tests/physics/test_golden.py).
"""

from .model import Control, MeshInfo, ModelBuilder, SpringMassModel, State, check_device, radius_springs
from .params import SimParams
from .solver import SimulationDiverged, SpringMassSolver, check_divergence

__all__ = [
    "Control",
    "MeshInfo",
    "ModelBuilder",
    "SimParams",
    "SimulationDiverged",
    "SpringMassModel",
    "SpringMassSolver",
    "State",
    "check_device",
    "check_divergence",
    "radius_springs",
]
