"""twinbench.physics: PhysTwin-compatible spring-mass simulation in NVIDIA Warp (CPU and CUDA)."""

from .model import Control, MeshInfo, ModelBuilder, SpringMassModel, State, radius_springs
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
    "check_divergence",
    "radius_springs",
]
