"""`twinbench align-robot seg/robot.ply --out aligned/ --also seg/background.ply`: register the robot's
Gaussians to the URDF (RANSAC + ICP), label them by link, move the other parts of the scan along."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from twinbench.construct.align_robot import RegistrationParams, align_robot_files


@dataclass(frozen=True)
class AlignRobotConfig:
    """Register robot Gaussians to the URDF at a known configuration and label them by link."""

    robot: Annotated[Path, tyro.conf.Positional]
    """the robot's Gaussians (e.g. segment's robot.ply)"""
    out: Path
    """output folder: robot.ply (world frame), labels.npz, far.ply, report.json, and the --also files"""
    urdf: str = "builtin:xarm7_gripper"
    """URDF path or built-in name (builtin:xarm7_gripper, builtin:xarm7_pusher)"""
    q: tuple[float, ...] | None = None
    """joint configuration of the scan (default: the robot's home)"""
    scale: bool = False
    """also estimate a uniform scale (scans of unknown units, e.g. COLMAP's: any unit)"""
    also: tuple[Path, ...] = ()
    """other parts of the same scan to move into the robot base frame (background, objects)"""
    max_distance: float = 0.02
    """Gaussians farther than this from every link after alignment go to far.ply, not to the robot (m)"""
    voxel: float = 0.012
    """global-registration voxel (m, robot units)"""
    min_inliers: float = 0.5
    """refuse the registration when fewer than this fraction of the Gaussians end within --max-distance"""
    seed: int = 0


def main(cfg: AlignRobotConfig) -> int:
    params = RegistrationParams(estimate_scale=cfg.scale, voxel=cfg.voxel, seed=cfg.seed)
    rep = align_robot_files(cfg.robot, cfg.out, urdf=cfg.urdf, q=cfg.q, params=params,
                            max_distance=cfg.max_distance, also=cfg.also,
                            min_inliers=cfg.min_inliers)
    print(f"fitness={rep['fitness']:.4f} rmse={rep['rmse_m'] * 1e3:.2f}mm scale={rep['scale']:.4f} "
          f"labelled={rep['labelled']} dropped={rep['dropped_far']}")
    return 0
