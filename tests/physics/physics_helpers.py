"""Small scene helpers shared by the physics tests (imported as a top-level module by pytest)."""

from __future__ import annotations

import numpy as np


def lattice(nx: int, ny: int, nz: int, spacing: float = 0.01, origin=(0.0, 0.0, 0.0)) -> np.ndarray:
    """Points of an nx x ny x nz lattice (x slowest, z fastest, as in the golden files)."""
    g = np.stack(np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"), -1).reshape(-1, 3)
    return g * spacing + np.asarray(origin, dtype=np.float64)
