"""`twinbench export-phystwin OBJECT_DIR --out CASE_DIR`: an object imported from PhysTwin, back as a
PhysTwin case folder."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from twinbench.construct.phystwin import export_object_to_case


@dataclass(frozen=True)
class ExportPhysTwinConfig:
    """Write a twin object imported from PhysTwin back as a PhysTwin case folder."""

    object_dir: Annotated[Path, tyro.conf.Positional]
    out: Path
    """case folder: final_data.pkl, optimal_params.pkl, train/best_EPOCH.pth"""


def main(cfg: ExportPhysTwinConfig) -> int:
    if not (cfg.object_dir / "phystwin.npz").is_file() or not (cfg.object_dir / "phystwin.json").is_file():
        raise SystemExit(
            f"export-phystwin: {cfg.object_dir} has no phystwin.npz/phystwin.json (only objects written by "
            "import-phystwin carry the case's tracking data PhysTwin needs)"
        )
    paths = export_object_to_case(cfg.object_dir, cfg.out)
    print(" ".join(str(p) for p in paths.values()))
    return 0
