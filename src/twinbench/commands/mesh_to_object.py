"""`twinbench mesh-to-object block.obj --spacing 0.005 --out objects/block`: a rigid spring-mass object
with surface Gaussians from a closed mesh."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from twinbench.construct.mesh_object import load_mesh, mesh_to_object
from twinbench.errors import check_name
from twinbench.twin import save_object


@dataclass(frozen=True)
class MeshToObjectConfig:
    """A rigid (very stiff) spring-mass object from a closed mesh, with surface Gaussians."""

    mesh: Annotated[Path, tyro.conf.Positional]
    """closed mesh (.obj/.stl/.ply), metres"""
    out: Path
    spacing: float = 0.005
    """particle lattice spacing (m)"""
    name: str = "object"
    spring_Y: float = 3e4
    radius_factor: float = 1.9
    """springs within radius_factor x spacing"""
    max_neighbors: int = 50
    rgb: tuple[float, float, float] = (0.6, 0.6, 0.6)
    """Gaussian colour"""


def main(cfg: MeshToObjectConfig) -> int:
    check_name(cfg.name, "--name")  # it names the object's files
    obj = mesh_to_object(load_mesh(cfg.mesh), name=cfg.name, spacing=cfg.spacing, spring_Y=cfg.spring_Y,
                         radius_factor=cfg.radius_factor, max_neighbors=cfg.max_neighbors, rgb=cfg.rgb)
    save_object(obj, cfg.out, sim={})
    print(f"particles={obj.num_particles} gaussians={len(obj.gaussians)} -> {cfg.out}")
    return 0
