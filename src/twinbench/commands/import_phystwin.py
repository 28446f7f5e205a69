"""`twinbench import-phystwin CASE_DIR --out objects/rope`: a trained PhysTwin case as a twin object
(read with the restricted loader)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from twinbench.construct.phystwin import import_case_to_object
from twinbench.errors import check_name


@dataclass(frozen=True)
class ImportPhysTwinConfig:
    """Import a trained PhysTwin case (final_data.pkl, optimal_params.pkl, best_*.pth) as a twin object."""

    case_dir: Annotated[Path, tyro.conf.Positional]
    """case folder holding final_data.pkl, optimal_params.pkl and best_EPOCH.pth (or train/best_EPOCH.pth)"""
    out: Path
    """object folder to write (object.json + arrays + phystwin.npz/json for export)"""
    name: str = "object"
    final_data: Path | None = None
    optimal_params: Path | None = None
    checkpoint: Path | None = None
    reverse_z: bool = True
    """the case uses PhysTwin's reverse_z frame (its real-data configs do)"""
    self_collision: bool = False
    """the case was trained with self_collision (PhysTwin's cloth config)"""
    gaussians: Path | None = None
    """optional object Gaussians in the case's frame (PhysTwin's gaussian_output .ply)"""


def main(cfg: ImportPhysTwinConfig) -> int:
    check_name(cfg.name, "--name")  # it names the object's files
    imp = import_case_to_object(cfg.case_dir, cfg.out, name=cfg.name, final_data=cfg.final_data,
                                optimal_params=cfg.optimal_params, checkpoint=cfg.checkpoint,
                                reverse_z=cfg.reverse_z, self_collision=cfg.self_collision,
                                gaussians=cfg.gaussians)
    print(f"particles={len(imp.particles)} springs={len(imp.springs)} "
          f"controller_springs={len(imp.controller_springs)} -> {cfg.out}")
    return 0
