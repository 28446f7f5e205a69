"""A rigid (very stiff) spring-mass object from a closed mesh, with surface Gaussians (DESIGN §4, the
reference cell's T-block): particles on a volume lattice inside the mesh plus surface samples, springs
within a radius (max 50 neighbours), uniform stiffness."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from twinbench.twin.assets import mesh_surface_gaussians
from twinbench.twin.spec import ObjectSpec


def load_mesh(path) -> trimesh.Trimesh:
    """A single triangle mesh from .obj/.stl/.ply (scenes are merged)."""
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:  # noqa: BLE001 - trimesh raises many types on bad files
        raise ValueError(f"{path}: cannot read the mesh ({exc})") from exc
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise ValueError(f"{path}: no triangles found")
    return mesh


MAX_PARTICLES = 2_000_000  # lattice points and surface samples of one object


def mesh_particles(mesh: trimesh.Trimesh, spacing: float) -> np.ndarray:
    """Lattice points inside the closed mesh plus evenly spread surface points (at least `spacing / 2`
    from every lattice point), float32 (N, 3)."""
    if not (np.isfinite(spacing) and spacing > 0):
        raise ValueError(f"spacing: must be a finite length > 0 (m), got {spacing}")
    if not mesh.is_watertight:
        raise ValueError("mesh is not closed (watertight): fill its holes first, a volume is needed")
    lo, hi = mesh.bounds
    count = float(np.prod((hi - lo) / spacing + 1)) + mesh.area / spacing**2
    if not count <= MAX_PARTICLES:
        raise ValueError(f"spacing: {spacing} m would give about {count:.3g} particles for this "
                         f"{np.round(hi - lo, 4).tolist()} m mesh (at most {MAX_PARTICLES}); use a larger "
                         "spacing")
    axes = [np.arange(lo[k] + 0.5 * ((hi[k] - lo[k]) % spacing), hi[k] + 1e-9, spacing) for k in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    inside = grid[mesh.contains(grid)] if len(grid) else grid
    count = max(int(round(mesh.area / spacing**2)), 4)
    surf, _ = trimesh.sample.sample_surface_even(mesh, count, radius=0.9 * spacing, seed=0)
    if len(inside):
        d, _ = cKDTree(inside).query(surf)
        surf = surf[d >= 0.5 * spacing]
    pts = np.concatenate([inside, surf]).astype(np.float32)
    if len(pts) < 4:
        raise ValueError(f"spacing {spacing} is too coarse for this mesh (got {len(pts)} particles)")
    return pts


def mesh_to_object(
    mesh: trimesh.Trimesh,
    *,
    name: str,
    spacing: float = 0.005,
    spring_Y: float = 3e4,
    radius_factor: float = 1.9,
    max_neighbors: int = 50,
    rgb=(0.6, 0.6, 0.6),
    gaussian_spacing: float | None = None,
    rest_pose=None,
) -> ObjectSpec:
    """The ObjectSpec of a rigid spring-mass body made from `mesh` (object frame = mesh frame); springs
    by the radius rule (`radius_factor` x spacing), Gaussians on the surface, rigid binding."""
    colour = np.asarray(rgb, dtype=np.float64)
    if colour.shape != (3,) or not np.all((colour >= 0) & (colour <= 1)):  # NaN fails too
        raise ValueError(f"rgb: expected 3 values in [0, 1], got {np.asarray(rgb).tolist()}")
    if isinstance(max_neighbors, bool) or not isinstance(max_neighbors, int | np.integer) \
            or not 1 <= max_neighbors <= 1000:
        raise ValueError(f"max_neighbors: expected an integer in [1, 1000] (springs per particle), got "
                         f"{max_neighbors!r}")
    if not 1.0 <= radius_factor <= 10.0:
        raise ValueError(f"radius_factor: expected a number in [1, 10] (x spacing), got {radius_factor}")
    if not (np.isfinite(spring_Y) and spring_Y > 0):
        raise ValueError(f"spring_Y: expected a finite stiffness > 0, got {spring_Y}")
    pts = mesh_particles(mesh, spacing)
    gs = spacing * 0.6 if gaussian_spacing is None else gaussian_spacing
    return ObjectSpec(
        name,
        pts,
        spring_Y=float(spring_Y),
        spring_radius=radius_factor * spacing,
        max_neighbors=int(max_neighbors),
        gaussians=mesh_surface_gaussians(mesh, colour, spacing=gs),
        binding="rigid",
        rest_pose=np.eye(4) if rest_pose is None else rest_pose,
    )
