"""Writes this folder: a PhysTwin-like rope (twinbench.construct.sysid_synthetic.phystwin_rope_case, seed 0)
as a sysid directory (sysid.json + data.npz) and its hidden truth (truth.npz: per-spring log Y, region,
springs, noise-free positions). Run from the repository root: python tests/data/sysid_rope/make.py"""

from pathlib import Path

import numpy as np

from twinbench.construct.sysid_io import save_sysid_data
from twinbench.construct.sysid_synthetic import phystwin_rope_case

here = Path(__file__).parent
data, truth = phystwin_rope_case(seed=0)
save_sysid_data(data, here)
p = truth["params"]
np.savez_compressed(here / "truth.npz", log_y=truth["log_y"], region=truth["region"],
                    springs=truth["springs"],
                    positions=truth["positions"].astype(np.float32), substeps=truth["sim"].substeps,
                    ground_restitution=p.ground_restitution, ground_friction=p.ground_friction,
                    drag_damping=p.drag_damping, dashpot_damping=p.dashpot_damping,
                    control_radius=p.control_radius, control_max_neighbors=p.control_max_neighbors)
