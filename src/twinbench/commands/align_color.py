"""`twinbench align-color --pairs pairs/ --gaussians aligned/robot.ply --out color/`: fit the rendered ->
real colour map (IRLS, Tukey) and apply it to Gaussians."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from twinbench.construct.align_color import align_color_files, render_pairs


@dataclass(frozen=True)
class AlignColorConfig:
    """Fit the colour map rendered -> real (IRLS, Tukey) and apply it to Gaussians' base colours."""

    out: Path
    """output folder: color_map.json, grid.png, the mapped .ply files, pairs/ (when rendered here)"""
    pairs: Path | None = None
    """folder of NAME_render.png / NAME_real.png (+ NAME_mask.png) pairs"""
    scan: tuple[Path, ...] = ()
    """instead of --pairs: Gaussians (world frame) to render from the calibrated cameras ..."""
    calibration: Path | None = None
    """... camera calibration file (see twinbench.construct.calibration) ..."""
    real: Path | None = None
    """... and a folder of real images NAME.png, one per camera name"""
    gaussians: tuple[Path, ...] = ()
    """.ply files to map (each written to OUT/<name>.ply)"""
    degree: int = 2
    iterations: int = 50


def main(cfg: AlignColorConfig) -> int:
    cfg.out.mkdir(parents=True, exist_ok=True)
    if cfg.pairs is None:
        if not (cfg.scan and cfg.calibration and cfg.real):
            raise SystemExit(
                "align-color: give --pairs DIR, or --scan, --calibration and --real to render pairs"
            )
        pairs_dir = cfg.out / "pairs"
        render_pairs(cfg.scan, cfg.calibration, cfg.real, pairs_dir)
    else:
        pairs_dir = cfg.pairs
    count, fit = align_color_files(pairs_dir, cfg.out, cfg.gaussians, degree=cfg.degree,
                                   iterations=cfg.iterations)
    print(f"pairs={count} iterations={fit.iterations} residual_sigma={fit.scale:.4f}")
    return 0
