"""Global simulation parameters (PhysTwin defaults, DESIGN section 4)."""

from __future__ import annotations

import math
from dataclasses import dataclass

COLLISION_EXCLUSIONS = ("springs", "none")


@dataclass(frozen=True)
class SimParams:
    """Parameters shared by every body of a spring-mass model.

    Particle-particle candidates are listed once per frame for pairs closer than
    ``candidate_radius_scale * collision_dist`` (1.0 is PhysTwin's rule; raise it when bodies move more
    than ``collision_dist`` per frame, otherwise fast pairs pass through each other). The per-substep
    contact test always uses ``collision_dist``. ``collision_exclusion`` picks which pairs never collide:
    ``"springs"`` (default, twinbench) skips spring-connected particles; ``"none"`` is PhysTwin's rule
    (every pair of different masks within ``collision_dist`` may collide, spring-connected or not), so a
    twin trained in PhysTwin simulates as it was trained. The two agree unless a spring is shorter than
    ``collision_dist`` (or is compressed below it). Units are SI. ``substeps`` defaults to
    ``round(1 / (30 * dt)) = 667`` (one 30 Hz frame is ``substeps * dt = 0.03335 s``, as in PhysTwin).
    Restitution is clamped to [0, 1] and friction to [0, 2] inside the kernels. Springs whose
    ``exp(logY) <= spring_Y_min`` are inactive. ``mesh_margin`` is the contact distance of triangle
    meshes; ``ground`` switches the z = 0 plane.
    """

    dt: float = 5e-5
    substeps: int = 667
    gravity: tuple[float, float, float] = (0.0, 0.0, -9.8)
    dashpot_damping: float = 100.0
    drag_damping: float = 3.0
    ground: bool = True
    ground_restitution: float = 0.5
    ground_friction: float = 0.3
    object_collision: bool = True
    object_restitution: float = 0.7
    object_friction: float = 0.3
    collision_dist: float = 0.02
    self_collision: bool = False
    collision_exclusion: str = "springs"
    max_collision_candidates: int = 500
    candidate_radius_scale: float = 1.0
    mesh_margin: float = 0.005
    spring_Y_min: float = 0.0
    spring_Y_max: float = 1e5

    def __post_init__(self) -> None:
        checks = {
            "dt": self.dt > 0 and math.isfinite(self.dt),
            "substeps": isinstance(self.substeps, int) and self.substeps >= 1,
            "dashpot_damping": self.dashpot_damping >= 0,
            "drag_damping": self.drag_damping >= 0,
            "collision_dist": self.collision_dist > 0,
            "mesh_margin": self.mesh_margin >= 0,
            "max_collision_candidates": self.max_collision_candidates >= 1,
            "candidate_radius_scale": self.candidate_radius_scale >= 1.0,
            "spring_Y_max": self.spring_Y_max > self.spring_Y_min >= 0,
            "gravity": len(self.gravity) == 3 and all(math.isfinite(g) for g in self.gravity),
            "collision_exclusion": self.collision_exclusion in COLLISION_EXCLUSIONS,
        }
        for name, ok in checks.items():
            if not ok:
                raise ValueError(f"SimParams.{name}={getattr(self, name)!r} is invalid (see its docstring)")

    @property
    def frame_dt(self) -> float:
        """Duration of one frame (all substeps), in seconds."""
        return self.dt * self.substeps
