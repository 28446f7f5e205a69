"""Per-channel polynomial colour maps applied to the Gaussians' base colour (DESIGN §6).

A colour map of degree d sends a base colour p = (r, g, b) to `A @ phi(p)`, where `phi` lists every
monomial r^i g^j b^k with i + j + k <= d (cross-channel terms included), ordered by total degree, then
by descending powers of r, g, b: degree 1 -> [1, r, g, b]; degree 2 -> [1, r, g, b, r^2, rg, rb, g^2,
gb, b^2]. `A` is (3, F). Applying a map rewrites the SH DC term so that the base colour
0.5 + C0 * dc becomes the mapped colour; the higher SH bands are left as they are.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from twinbench.gaussians.cloud import SH_C0, GaussianCloud


@lru_cache(maxsize=8)
def monomial_exponents(degree: int) -> np.ndarray:
    """(F, 3) exponents (i, j, k) of the monomials r^i g^j b^k of total degree <= `degree`, in phi order."""
    if int(degree) != degree or degree < 1:
        raise ValueError(f"colour map degree must be an integer >= 1, got {degree!r}")
    rows = []
    for total in range(int(degree) + 1):
        for i in range(total, -1, -1):
            for j in range(total - i, -1, -1):
                rows.append((i, j, total - i - j))
    out = np.array(rows, dtype=np.int64)
    out.flags.writeable = False
    return out


def polynomial_features(rgb, degree: int = 2) -> np.ndarray:
    """phi(p) for colours `rgb` (..., 3): (..., F) float64 features (see the module docstring)."""
    p = np.asarray(rgb, dtype=np.float64)
    if p.shape[-1:] != (3,):
        raise ValueError(f"rgb must have shape (..., 3), got {p.shape}")
    e = monomial_exponents(degree)
    return np.prod(p[..., None, :] ** e, axis=-1)


def identity_color_map(degree: int = 2) -> np.ndarray:
    """The (3, F) coefficients of the identity map at `degree`."""
    coeffs = np.zeros((3, len(monomial_exponents(degree))))
    coeffs[:, 1:4] = np.eye(3)
    return coeffs


def check_color_map(coeffs, degree: int) -> np.ndarray:
    """Validate (3, F) finite coefficients for `degree`; returns them as float64."""
    a = np.asarray(coeffs, dtype=np.float64)
    f = len(monomial_exponents(degree))
    if a.shape != (3, f):
        raise ValueError(f"colour map of degree {degree} needs coefficients of shape (3, {f}), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError("colour map coefficients contain NaN or inf")
    return a


def map_colors(rgb, coeffs, degree: int = 2) -> np.ndarray:
    """Mapped colours A @ phi(rgb), (..., 3) float64 (not clamped)."""
    a = check_color_map(coeffs, degree)
    return polynomial_features(rgb, degree) @ a.T


def apply_color_map(cloud: GaussianCloud, coeffs, degree: int = 2) -> GaussianCloud:
    """A copy of `cloud` whose base colours are mapped by the colour map (SH DC rewritten)."""
    mapped = map_colors(cloud.base_colours, coeffs, degree)
    out = cloud.copy()
    out.sh[:, 0] = ((mapped - 0.5) / SH_C0).astype(np.float32)
    return out
