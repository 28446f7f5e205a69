"""`twinbench refine-cameras --scan aligned/robot.ply ... --calibration calibration.json --real real/ --out
cameras/`: correct each static camera's pose and intrinsics so that the scan's render lines up with its real
image (`twinbench.construct.refine_camera`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from twinbench.construct.refine_camera import BLURS, PRIOR, refine_camera_files


@dataclass(frozen=True)
class RefineCamerasConfig:
    """Refine each static camera of a calibration on its real image of the scanned workcell."""

    scan: tuple[Path, ...]
    """Gaussians of the workcell in the robot's frame (align-robot's output: robot, background, objects)"""
    calibration: Path
    """camera calibration file (see twinbench.construct.calibration)"""
    real: Path
    """folder of real images NAME.png (one per static camera), of the workcell as scanned"""
    out: Path
    """output folder: calibration.json (refined), refine.json, NAME_residual.png"""
    blurs: tuple[float, ...] = BLURS
    """image blurs (px) of the coarse-to-fine search"""
    prior: float = PRIOR
    """pull toward the calibration (squared change in search units, against the image residual)"""
    max_evals: int = 1000
    """at most this many renders per blur"""


def main(cfg: RefineCamerasConfig) -> int:
    fits = refine_camera_files(cfg.scan, cfg.calibration, cfg.real, cfg.out, blurs=cfg.blurs,
                               prior=cfg.prior, max_evals=cfg.max_evals)
    for name, f in fits.items():
        state = "refined" if f.adopted else "kept as calibrated (no lower residual)"
        fx, fy, cx, cy = f.intrinsics_change
        print(f"{name}: {state}; residual {f.rms_before:.2f} -> {f.rms_after:.2f} levels; image moved "
              f"{f.shift_px:.2f} px (median): "
              f"{f.rotation_deg:.3f} deg, {1000 * f.translation_m:.2f} mm; fx {100 * fx:+.2f} %, "
              f"fy {100 * fy:+.2f} %, cx {cx:+.2f} px, cy {cy:+.2f} px ({f.evaluations} renders)")
    print(f"wrote {cfg.out / 'calibration.json'}")
    return 0
