"""Disc primitives: orientation and parameters with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.gaussians.primitives import quat_z_to, surface_discs
from twinbench.transforms import quat_to_matrix


def test_quat_z_to_maps_z_onto_each_normal():
    rng = np.random.default_rng(0)
    n = rng.normal(size=(50, 3))
    n = np.vstack([n / np.linalg.norm(n, axis=1, keepdims=True), [[0, 0, 1.0], [0, 0, -1.0]]])
    rot = quat_to_matrix(quat_z_to(n))
    np.testing.assert_allclose(rot[:, :, 2], n, atol=1e-12)


def test_surface_discs_parameters():
    pts = np.zeros((2, 3))
    normals = np.array([[0, 0, 1.0], [1.0, 0, 0]])
    discs = surface_discs(pts, normals, (0.2, 0.5, 0.9), radius=0.01, opacity=0.8, thickness=0.1)
    np.testing.assert_allclose(discs.scales, [[0.01, 0.01, 0.001]] * 2, rtol=1e-6)
    np.testing.assert_allclose(discs.opacities, 0.8, rtol=1e-6)
    np.testing.assert_allclose(discs.base_colours, [[0.2, 0.5, 0.9]] * 2, atol=1e-6)
    # the thin axis (local z) lies along the normal
    np.testing.assert_allclose(quat_to_matrix(discs.quats)[:, :, 2], normals, atol=1e-6)
    with pytest.raises(ValueError, match="opacity"):
        surface_discs(pts, normals, (0, 0, 0), radius=0.01, opacity=1.0)
