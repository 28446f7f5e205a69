"""Golden agreement: max |dx| over every frame of each PhysTwin golden trajectory (tests/data/phystwin, or
$TWINBENCH_GOLDEN_DIR), one line per file. 0.0 means bit-identical to PhysTwin's own simulator.

    python benchmarks/golden.py
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np


def main() -> None:
    from twinbench._runtime import quiet_warp

    quiet_warp()
    from twinbench.physics import SpringMassSolver
    from twinbench.physics.golden import golden_model, load_golden

    folder = Path(os.environ.get("TWINBENCH_GOLDEN_DIR") or Path(__file__).parents[1] / "tests/data/phystwin")
    for path in sorted(folder.glob("*.npz")):
        g = load_golden(path)
        model = golden_model(g)
        solver = SpringMassSolver(model)
        state, ctl = model.state(), model.control()
        worst = 0.0
        for k in range(1, int(g["n_frames"]) + 1):
            if model.num_control_points:
                ctl.set_control_points(g["control_points_frames"][k - 1], g["control_points_frames"][k])
            solver.simulate_frame(state, ctl)
            worst = max(worst, float(np.abs(state.x.numpy() - g["x_frames"][k]).max()))
        print(f"golden {path.stem}: max |dx| over {int(g['n_frames'])} frames = {worst:.3g} m", flush=True)


if __name__ == "__main__":
    main()
