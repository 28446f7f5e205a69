"""Colour maps: monomial order, identity, and a known map applied to a cloud's base colour."""

import numpy as np
import pytest

from twinbench.gaussians.colormap import (
    apply_color_map,
    identity_color_map,
    monomial_exponents,
    polynomial_features,
)
from twinbench.gaussians.primitives import surface_discs


def test_monomials_in_documented_order():
    np.testing.assert_array_equal(monomial_exponents(1), [[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
    e2 = monomial_exponents(2)
    assert len(e2) == 10
    np.testing.assert_array_equal(e2[4:], [[2, 0, 0], [1, 1, 0], [1, 0, 1], [0, 2, 0], [0, 1, 1], [0, 0, 2]])
    assert len(monomial_exponents(3)) == 20
    phi = polynomial_features([0.5, 0.2, 0.1], 2)
    np.testing.assert_allclose(phi, [1, 0.5, 0.2, 0.1, 0.25, 0.1, 0.05, 0.04, 0.02, 0.01])
    with pytest.raises(ValueError, match="degree"):
        monomial_exponents(0)


def test_identity_keeps_and_known_map_sets_base_colour():
    rng = np.random.default_rng(0)
    rgb = rng.uniform(0.1, 0.9, (50, 3))
    cloud = surface_discs(
        rng.normal(size=(50, 3)).astype(np.float32), np.tile([0.0, 0, 1], (50, 1)), rgb, 0.01
    )
    same = apply_color_map(cloud, identity_color_map(2), 2)
    np.testing.assert_allclose(same.base_colours, cloud.base_colours, atol=1e-6)
    coeffs = identity_color_map(2) * 0.0
    coeffs[0, 0], coeffs[0, 4] = 0.1, 0.8  # r' = 0.1 + 0.8 r^2
    coeffs[1, 2] = 0.5  # g' = 0.5 g
    coeffs[2, 5] = 2.0  # b' = 2 r g (cross-channel)
    out = apply_color_map(cloud, coeffs, 2)
    r, g, _ = cloud.base_colours.astype(np.float64).T
    np.testing.assert_allclose(out.base_colours, np.c_[0.1 + 0.8 * r**2, 0.5 * g, 2 * r * g], atol=1e-5)
    np.testing.assert_array_equal(out.means, cloud.means)
    with pytest.raises(ValueError, match="shape"):
        apply_color_map(cloud, np.zeros((3, 4)), 2)
