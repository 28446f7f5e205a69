"""Object geometry as twin data: `Outline` (a footprint polygon extruded to a height, the shape that
planar tasks such as push-T read from `ObjectSpec.outline`) and the built-in T-block (`TBlockShape`, its
particles, its mesh) that the built-in push-T cell is made of.

Pure NumPy (trimesh only for `TBlockShape.mesh`). Object frame: the footprint lies in the xy plane, z
from 0 (table) to `height`. The built-in T's frame has its origin at the T's area centroid; its bar lies
along x and its stem points along -y.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class Outline:
    """A prism: the simple polygon `polygon` (K, 2), counter-clockwise, in the object frame's xy plane,
    extruded from z = 0 to `height` (metres). Push-T reads its block's footprint, goal overlay and
    contact points from it."""

    polygon: np.ndarray
    height: float

    def __post_init__(self) -> None:
        p = np.array(self.polygon, dtype=np.float64)  # an own, read-only copy: its edges are kept below
        if p.ndim != 2 or p.shape[1] != 2 or len(p) < 3 or not np.all(np.isfinite(p)):
            raise ValueError(
                f"outline.polygon: expected a finite (K, 2) array with K >= 3, got shape {p.shape}"
            )
        h = float(self.height)
        if not (np.isfinite(h) and h > 0):
            raise ValueError(f"outline.height: expected a finite number > 0, got {self.height!r}")
        p.flags.writeable = False
        object.__setattr__(self, "polygon", p)
        object.__setattr__(self, "height", h)
        a, b = p, np.roll(p, -1, axis=0)
        object.__setattr__(self, "_ends", (a, b))  # every edge's two ends
        slanted = a[:, 1] != b[:, 1]  # a horizontal edge never straddles a point's ray
        object.__setattr__(self, "_slanted", (a[slanted], b[slanted]))
        if not self.area > 0:
            raise ValueError("outline.polygon: the vertices must go counter-clockwise (seen from +z) and "
                             "enclose a positive area")

    @property
    def area(self) -> float:
        """Signed area of the polygon (positive: counter-clockwise), m^2."""
        a, b = self._ends
        return 0.5 * float(np.sum(a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]))

    def polar_radius2(self) -> float:
        """Mean squared distance of the footprint from the frame origin (polar second moment / area), m^2."""
        a, b = self._ends
        cross = a[:, 0] * b[:, 1] - b[:, 0] * a[:, 1]
        sq = a[:, 0] ** 2 + a[:, 0] * b[:, 0] + b[:, 0] ** 2 + a[:, 1] ** 2 + a[:, 1] * b[:, 1] + b[:, 1] ** 2
        return float(np.sum(cross * sq)) / 12.0 / self.area

    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """(min, max) corners of the prism's axis-aligned bounding box, (3,) each."""
        return np.r_[self.polygon.min(0), 0.0], np.r_[self.polygon.max(0), self.height]

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether object-frame points lie inside the prism, boundary included (within `tol`): (N, 3)
        points, or (N, 2) for the footprint alone."""
        p = np.asarray(points, dtype=np.float64)
        # only points within tol of the bounding box can be inside or on the boundary
        lo, hi = self.polygon.min(0) - tol, self.polygon.max(0) + tol
        boxed = np.flatnonzero(np.all((p[:, :2] >= lo) & (p[:, :2] <= hi), axis=1))
        inside = np.zeros(len(p), dtype=bool)
        inside[boxed] = self._in_polygon(p[boxed, :2])
        # the boundary test only where it can change the answer: outside, within tol of the bounding box
        near = boxed[~inside[boxed]]
        inside[near] = self._within(p[near, :2], tol)
        if p.shape[1] == 3:
            inside &= (p[:, 2] >= -tol) & (p[:, 2] <= self.height + tol)
        return inside

    def nearest(self, point) -> np.ndarray:
        """The footprint's nearest point to a 2D object-frame point (the point itself when inside)."""
        p = np.asarray(point, dtype=np.float64)[:2]
        if self._in_polygon(p[None])[0]:
            return p
        q = self._closest_on_edges(p[None])[0]
        return q[np.argmin(np.linalg.norm(q - p, axis=1))]

    def distance(self, point) -> float:
        """Distance from a 2D object-frame point to the footprint (0 inside)."""
        p = np.asarray(point, dtype=np.float64)[:2]
        return float(np.linalg.norm(p - self.nearest(p)))

    def scaled(self, factor: float) -> Outline:
        """The outline scaled by `factor` about the frame origin (height included)."""
        return Outline(self.polygon * factor, self.height * factor)

    def _in_polygon(self, p: np.ndarray) -> np.ndarray:
        """Even-odd rule: (N,) whether the (N, 2) points are strictly inside (boundary: either)."""
        a, b = self._slanted
        px, py = p[:, :1], p[:, 1:2]
        straddle = (a[:, 1] > py) != (b[:, 1] > py)
        x_cross = a[:, 0] + (py - a[:, 1]) * (b[:, 0] - a[:, 0]) / (b[:, 1] - a[:, 1])
        return np.count_nonzero(straddle & (px < x_cross), axis=1) % 2 == 1

    def _closest_on_edges(self, p: np.ndarray) -> np.ndarray:
        """(N, K, 2): the closest point of each edge to each point."""
        a, b = self._ends
        e = b - a
        t = np.einsum("nkd,kd->nk", p[:, None, :] - a, e) / np.sum(e * e, axis=1)
        return a + np.clip(t, 0.0, 1.0)[..., None] * e

    def _within(self, p: np.ndarray, tol: float) -> np.ndarray:
        """(N,) whether the (N, 2) points lie within `tol` of the boundary: the distance computed only for
        the points inside some edge's bounding box widened by `tol` (no other point can be that close)."""
        a, b = self._ends
        lo, hi = np.minimum(a, b) - tol, np.maximum(a, b) + tol
        x, y = p[:, :1], p[:, 1:2]
        boxed = (x >= lo[:, 0]) & (x <= hi[:, 0]) & (y >= lo[:, 1]) & (y <= hi[:, 1])
        rows = np.flatnonzero(np.any(boxed, axis=1))
        out = np.zeros(len(p), dtype=bool)
        q = p[rows]
        out[rows] = np.min(np.linalg.norm(self._closest_on_edges(q) - q[:, None, :], axis=2), axis=1) <= tol
        return out


@dataclass(frozen=True)
class TBlockShape:
    """A T made of a bar (along x) on top of a stem (along -y), extruded by `height` (metres)."""

    bar_length: float = 0.12
    bar_width: float = 0.03
    stem_length: float = 0.09
    stem_width: float = 0.03
    height: float = 0.03

    def scaled(self, factor: float) -> TBlockShape:
        """The T with every dimension multiplied by `factor`."""
        f = float(factor)
        return TBlockShape(self.bar_length * f, self.bar_width * f, self.stem_length * f,
                           self.stem_width * f, self.height * f)

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

    def outline(self) -> Outline:
        """The T as twin data (`ObjectSpec.outline`)."""
        return Outline(self.outline_xy(), self.height)

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
