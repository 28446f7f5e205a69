"""Helpers for the gaussians tests: random clouds and the brute-force NumPy reference renderer (in the
package: twinbench.gaussians.reference)."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.reference import reference_render


def random_cloud(
    n: int,
    *,
    degree: int = 0,
    seed: int = 0,
    center=(0.0, 0.0, 0.0),
    spread: float = 0.3,
    log_scale=(-4.0, -2.5),
    anisotropic: bool = False,
) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    means = np.asarray(center) + rng.uniform(-spread, spread, size=(n, 3))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    log_scales = rng.uniform(*log_scale, size=(n, 3))
    if anisotropic:
        # thin discs (one axis ~30x shorter) and, for a third of them, needles (two short axes)
        axis = rng.integers(0, 3, size=n)
        log_scales[np.arange(n), axis] -= 3.5
        needles = rng.random(n) < 1 / 3
        log_scales[np.flatnonzero(needles), (axis[needles] + 1) % 3] -= 3.5
    k = (degree + 1) ** 2
    sh = rng.normal(scale=0.4, size=(n, k, 3))
    sh[:, 1:] *= 0.5
    return GaussianCloud(means, quats, log_scales, rng.uniform(-2.0, 4.0, size=n), sh)


@pytest.fixture
def make_cloud():
    return random_cloud


@pytest.fixture
def ref_render():
    return reference_render
