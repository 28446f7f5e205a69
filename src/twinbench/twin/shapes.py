"""Push-T geometry: the T-block shape, its particles, the grid of initial states and the goal distance
(DESIGN §7).

Pure NumPy: no physics or rendering here, so the rules can be checked on their own.
Block frame: origin at the T's area centroid in the xy plane, z from 0 (table) to `height`; the bar
lies along x and the stem points along -y.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TBlockShape:
    """A T made of a bar (along x) on top of a stem (along -y), extruded by `height` (metres)."""

    bar_length: float = 0.12
    bar_width: float = 0.03
    stem_length: float = 0.09
    stem_width: float = 0.03
    height: float = 0.03

    def boxes_raw(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(min, max) corners of bar and stem in a frame with the bar's top edge at y = 0."""
        bar = (np.array([-self.bar_length / 2, -self.bar_width, 0.0]),
               np.array([self.bar_length / 2, 0.0, self.height]))
        stem = (np.array([-self.stem_width / 2, -self.bar_width - self.stem_length, 0.0]),
                np.array([self.stem_width / 2, -self.bar_width, self.height]))
        return [bar, stem]

    @property
    def centroid_y(self) -> float:
        """y of the area centroid in the raw frame (bar top edge at y = 0)."""
        a_bar = self.bar_length * self.bar_width
        a_stem = self.stem_width * self.stem_length
        y_bar = -self.bar_width / 2
        y_stem = -self.bar_width - self.stem_length / 2
        return (a_bar * y_bar + a_stem * y_stem) / (a_bar + a_stem)

    def boxes(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """(min, max) corners of bar and stem in the block frame (area centroid at the origin)."""
        shift = np.array([0.0, -self.centroid_y, 0.0])
        return [(lo + shift, hi + shift) for lo, hi in self.boxes_raw()]

    def polar_radius2(self) -> float:
        """Mean squared distance of the T's footprint from its centroid (polar second moment / area), m^2."""
        total = moment = 0.0
        for lo, hi in self.boxes():
            w, h = hi[0] - lo[0], hi[1] - lo[1]
            c = 0.5 * (lo[:2] + hi[:2])
            area = w * h
            total += area
            moment += area * (float(c @ c) + (w * w + h * h) / 12.0)
        return moment / total

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether block-frame points lie inside the T (boundary included)."""
        p = np.asarray(points, dtype=np.float64)
        inside = np.zeros(len(p), dtype=bool)
        for lo, hi in self.boxes():
            inside |= np.all((p >= lo - tol) & (p <= hi + tol), axis=1)
        return inside

    def outline_xy(self) -> np.ndarray:
        """The T's outline polygon (8 vertices, counter-clockwise) in the block frame."""
        (blo, bhi), (slo, shi) = self.boxes()
        return np.array([
            [blo[0], blo[1]], [slo[0], blo[1]], [slo[0], slo[1]], [shi[0], slo[1]],
            [shi[0], blo[1]], [bhi[0], blo[1]], [bhi[0], bhi[1]], [blo[0], bhi[1]],
        ])

    def mesh(self):
        """A closed triangle mesh of the T (trimesh), built as a prism over the outline."""
        import trimesh

        outline = self.outline_xy()
        n = len(outline)
        bottom = np.c_[outline, np.zeros(n)]
        top = np.c_[outline, np.full(n, self.height)]
        vertices = np.vstack([bottom, top])
        # Caps: the bar (a hexagon, as vertices 1 and 4 lie on its lower edge) fanned from vertex 7,
        # and the stem rectangle; counter-clockwise triangles face +z.
        cap = [(7, 0, 1), (7, 1, 4), (7, 4, 5), (7, 5, 6), (1, 2, 3), (1, 3, 4)]
        faces = []
        for a, b, c in cap:
            faces += [[a, c, b], [a + n, b + n, c + n]]  # bottom (normal -z), top (normal +z)
        for i in range(n):
            j = (i + 1) % n
            faces += [[i, j, j + n], [i, j + n, i + n]]
        mesh = trimesh.Trimesh(vertices=vertices, faces=np.array(faces), process=True)
        return mesh


def sample_block_particles(shape: TBlockShape, spacing: float) -> np.ndarray:
    """Particles for a rigid spring-mass T: a volume lattice plus the lattice's outer faces.

    Points are on a regular grid of `spacing` clipped to the T, with the grid chosen so that the
    block's faces (including the top and bottom) carry particles. Returns (N, 3) in the block frame.
    """
    if not spacing > 0:
        raise ValueError(f"spacing must be positive, got {spacing}")
    (blo, bhi), (slo, shi) = shape.boxes()
    lo = np.minimum(blo, slo)
    hi = np.maximum(bhi, shi)
    axes = []
    for k in range(3):
        count = max(int(np.ceil((hi[k] - lo[k]) / spacing - 1e-9)), 1)
        axes.append(np.linspace(lo[k], hi[k], count + 1))
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    # The stem and bar faces lie on the lattice when the spacing divides the T's dimensions (5 mm,
    # 15 mm); the small tolerance keeps boundary points that round-off would drop.
    inside = shape.contains(grid, tol=1e-6)
    return grid[inside].astype(np.float32)


def grid_initial_states() -> np.ndarray:
    """The 16 reference initial states (dx, dy, dtheta) relative to the nominal pose.

    x, y in {-5, +5} cm and theta in {+-45, +-135} degrees (DESIGN §7).
    """
    states = [
        (dx, dy, np.deg2rad(th))
        for dx in (-0.05, 0.05)
        for dy in (-0.05, 0.05)
        for th in (-135.0, -45.0, 45.0, 135.0)
    ]
    return np.array(states)


def mean_squared_distance(particles: np.ndarray, goal_particles: np.ndarray) -> float:
    """Mean over particles of the squared distance to the same particle at the goal pose (m^2)."""
    d = np.asarray(particles, dtype=np.float64) - np.asarray(goal_particles, dtype=np.float64)
    return float(np.mean(np.sum(d * d, axis=1)))
