"""`twinbench segment SCAN --boxes boxes.json --out seg/`: split a workcell scan with crop boxes."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from twinbench.construct.segment import segment_files


@dataclass(frozen=True)
class SegmentConfig:
    """Split a workcell scan into robot / background / named objects with crop boxes."""

    scan: Annotated[Path, tyro.conf.Positional]
    """3DGS scan (.ply/.splat/.spz)"""
    boxes: Path
    """boxes JSON: optional coarse transform, robot, object and bounds boxes (twinbench.construct.segment)"""
    out: Path
    """output folder: robot.ply, background.ply, objects/NAME.ply, segments.npz, segments.json"""


def main(cfg: SegmentConfig) -> int:
    counts = segment_files(cfg.scan, cfg.boxes, cfg.out)
    print(" ".join(f"{k}={v}" for k, v in counts.items()))
    return 0
