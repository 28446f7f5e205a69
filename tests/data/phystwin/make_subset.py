"""Write the repository's copy of PhysTwin's golden trajectories from the full files.

The full files (about 19 MB) keep all 668 substep states of a few frames; the copy keeps every frame and
the substep states at `substep_index` (the first 10, then every 33rd, and the last), so the default tests
check every frame and 31 substeps of each saved frame, in about 1.3 MB. Run from the repository root:

    python tests/data/phystwin/make_subset.py /path/to/full/phystwin tests/data/phystwin
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

SUBSTEPS = np.unique(np.r_[np.arange(10), np.arange(0, 668, 33), 100, 667]).astype(np.int32)


def subset(src: Path, dst: Path) -> None:
    with np.load(src, allow_pickle=False) as data:
        arrays = {k: data[k] for k in data.files}
    for key in ("x_substeps", "v_substeps"):
        arrays[key] = arrays[key][:, SUBSTEPS]
    if "control_x_substeps" in arrays:  # control positions used by substep s + 1 (667 per frame)
        arrays["control_x_substeps"] = arrays["control_x_substeps"][:, SUBSTEPS[1:] - 1]
    arrays["substep_index"] = SUBSTEPS
    np.savez_compressed(dst, **arrays)


def main(src_dir: str, dst_dir: str) -> None:
    for src in sorted(Path(src_dir).glob("*.npz")):
        subset(src, Path(dst_dir) / src.name)
        print(src.name, (Path(dst_dir) / src.name).stat().st_size // 1024, "KiB")


if __name__ == "__main__":
    main(*sys.argv[1:3])
