"""Procedural workcell appearance (no download): textured table, backdrop, and object surface Gaussians.

Gaussians are flat discs lying in the surface (thin axis along the normal). Textures are procedural
(wood grain, tape marks, posters) so that images carry structure a vision policy can use.
"""

from __future__ import annotations

import numpy as np

from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.primitives import surface_discs


def _plane_points(origin, u, v, size_u: float, size_v: float, spacing: float, rng) -> np.ndarray:
    """Jittered grid on the rectangle origin + a u + b v, a in [0, size_u], b in [0, size_v]."""
    nu, nv = max(int(size_u / spacing), 1), max(int(size_v / spacing), 1)
    a, b = np.meshgrid(
        (np.arange(nu) + 0.5) / nu * size_u, (np.arange(nv) + 0.5) / nv * size_v, indexing="ij"
    )
    a = a.ravel() + rng.uniform(-0.25, 0.25, a.size) * spacing
    b = b.ravel() + rng.uniform(-0.25, 0.25, b.size) * spacing
    return np.asarray(origin) + a[:, None] * np.asarray(u) + b[:, None] * np.asarray(v)


def table_gaussians(
    x_range=(-0.25, 0.95), y_range=(-0.55, 0.55), spacing: float = 0.006, seed: int = 0
) -> GaussianCloud:
    """The table top (z = 0): wood grain along x, a tape frame around the push area, grid dots."""
    rng = np.random.default_rng(seed)
    pts = _plane_points(
        (x_range[0], y_range[0], 0.0),
        (1, 0, 0),
        (0, 1, 0),
        x_range[1] - x_range[0],
        y_range[1] - y_range[0],
        spacing,
        rng,
    )
    x, y = pts[:, 0], pts[:, 1]
    grain = 0.5 + 0.5 * np.sin(90.0 * y + 6.0 * np.sin(7.0 * x) + 3.0 * np.sin(23.0 * y))
    rgb = np.array([0.62, 0.45, 0.30]) * (0.85 + 0.2 * grain[:, None])
    rgb *= 1.0 + rng.normal(0.0, 0.03, (len(pts), 1))
    # Blue tape rectangle around the push area and black dots every 10 cm for scale.
    frame = (np.abs(np.abs(x - 0.45) - 0.2) < 0.008) & (np.abs(y) < 0.208)
    frame |= (np.abs(np.abs(y) - 0.2) < 0.008) & (np.abs(x - 0.45) < 0.208)
    rgb[frame] = (0.15, 0.30, 0.75)
    dots = (np.hypot((x + 0.05) % 0.1 - 0.05, (y + 0.05) % 0.1 - 0.05) < 0.006) & ~frame
    rgb[dots] = (0.08, 0.08, 0.08)
    normals = np.tile([0.0, 0.0, 1.0], (len(pts), 1))
    return surface_discs(pts.astype(np.float32), normals, rgb, 0.75 * spacing, opacity=0.98)


def backdrop_gaussians(
    x: float = -0.3, y_range=(-0.9, 0.9), z_range=(-0.2, 1.0), spacing: float = 0.012, seed: int = 1
) -> GaussianCloud:
    """A wall behind the robot (plane x = const, facing +x) with coloured posters and a skirting stripe."""
    rng = np.random.default_rng(seed)
    pts = _plane_points(
        (x, y_range[0], z_range[0]),
        (0, 1, 0),
        (0, 0, 1),
        y_range[1] - y_range[0],
        z_range[1] - z_range[0],
        spacing,
        rng,
    )
    y, z = pts[:, 1], pts[:, 2]
    rgb = np.tile([0.78, 0.79, 0.76], (len(pts), 1)) * (1.0 + rng.normal(0.0, 0.02, (len(pts), 1)))
    posters = [
        ((-0.55, 0.35, -0.25, 0.75), (0.80, 0.25, 0.20)),
        ((0.3, 0.4, 0.65, 0.7), (0.20, 0.55, 0.35)),
        ((0.5, 0.05, 0.75, 0.3), (0.95, 0.80, 0.20)),
    ]
    for (y0, z0, y1, z1), colour in posters:
        rgb[(y > y0) & (y < y1) & (z > z0) & (z < z1)] = colour
    rgb[z < 0.05] = (0.30, 0.30, 0.32)
    normals = np.tile([1.0, 0.0, 0.0], (len(pts), 1))
    return surface_discs(pts.astype(np.float32), normals, rgb, 0.8 * spacing, opacity=0.98)


def mesh_surface_gaussians(mesh, rgb, spacing: float = 0.003, seed: int = 0) -> GaussianCloud:
    """Disc Gaussians sampled evenly on a trimesh surface (count = area / spacing^2), one colour."""
    import trimesh

    if not spacing > 0:
        raise ValueError(f"spacing must be > 0, got {spacing}")
    count = max(int(round(mesh.area / spacing**2)), 1)
    pts, faces = trimesh.sample.sample_surface_even(mesh, count, seed=seed)
    normals = np.asarray(mesh.face_normals)[faces]
    return surface_discs(pts.astype(np.float32), normals, rgb, 0.75 * spacing, opacity=0.98)
