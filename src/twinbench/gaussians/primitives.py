"""Gaussian primitives: flat discs lying in a surface (synthetic scans, procedural assets)."""

from __future__ import annotations

import numpy as np

from twinbench.gaussians.cloud import SH_C0, GaussianCloud


def quat_z_to(normals: np.ndarray) -> np.ndarray:
    """wxyz quaternions rotating +z onto each unit normal (shortest arc; -z maps by a half turn about x)."""
    n = np.asarray(normals, dtype=np.float64)
    w = 1.0 + n[:, 2]
    q = np.stack([w, -n[:, 1], n[:, 0], np.zeros(len(n))], axis=1)
    q[w < 1e-8] = (0.0, 1.0, 0.0, 0.0)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def surface_discs(
    points: np.ndarray,
    normals: np.ndarray,
    rgb: np.ndarray,
    radius: float,
    *,
    opacity: float = 0.95,
    thickness: float = 0.1,
) -> GaussianCloud:
    """Disc Gaussians of scale (radius, radius, thickness*radius) lying in the surface, DC colour rgb."""
    n = len(points)
    rgb = np.broadcast_to(np.asarray(rgb, dtype=np.float64), (n, 3))
    if not 0.0 < opacity < 1.0:
        raise ValueError(f"opacity must be in (0, 1), got {opacity}")
    if not radius > 0:
        raise ValueError(f"radius must be > 0, got {radius}")
    log_s = np.log([radius, radius, thickness * radius])
    return GaussianCloud(
        means=points,
        quats=quat_z_to(normals),
        log_scales=np.broadcast_to(log_s, (n, 3)),
        logit_opacities=np.full(n, np.log(opacity / (1.0 - opacity))),
        sh=((np.clip(rgb, 0.0, 1.0) - 0.5) / SH_C0)[:, None, :],
    )
