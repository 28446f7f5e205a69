import numpy as np
import pytest

from twinbench.tasks.base import InitialStates, SuccessWindow, offset_pose
from twinbench.tasks.push_t import grid_initial_states, mean_squared_distance
from twinbench.transforms import planar_pose, transform_points
from twinbench.twin.shapes import TBlockShape, sample_block_particles


def test_t_mesh_is_closed_with_analytic_volume_and_centroid():
    shape = TBlockShape()
    mesh = shape.mesh()
    assert mesh.is_watertight and mesh.is_winding_consistent
    volume = (shape.bar_length * shape.bar_width + shape.stem_width * shape.stem_length) * shape.height
    assert mesh.volume == pytest.approx(volume, rel=1e-9)
    np.testing.assert_allclose(mesh.center_mass, [0, 0, shape.height / 2], atol=1e-12)


def test_particles_fill_the_t_on_a_lattice():
    shape = TBlockShape()
    pts = sample_block_particles(shape, 0.005)
    assert shape.contains(pts, tol=1e-6).all()
    # 5 mm lattice: bar 25 x 7 columns, stem 7 x 18 more columns below the bar, 7 layers.
    assert len(pts) == (25 * 7 + 7 * 18) * 7
    np.testing.assert_allclose(pts[:, 2].min(), 0.0, atol=1e-7)
    np.testing.assert_allclose(pts[:, 2].max(), shape.height, atol=1e-7)
    with pytest.raises(ValueError, match="spacing"):
        sample_block_particles(shape, 0.0)


def test_grid_states_are_the_16_reference_states():
    """The reference study's order: xy[i // 4], theta[i % 4]."""
    states = grid_initial_states()
    assert states.shape == (16, 3)
    assert len({tuple(np.round(s, 6)) for s in states}) == 16
    xy = [(-0.05, -0.05), (-0.05, 0.05), (0.05, -0.05), (0.05, 0.05)]
    for i, (dx, dy, th) in enumerate(states):
        assert (dx, dy) == pytest.approx(xy[i // 4], abs=1e-12)
        assert np.rad2deg(th) == pytest.approx([45.0, 135.0, 225.0, 315.0][i % 4], abs=1e-9)


def test_initial_states_are_data_with_a_seeded_sampler_and_products():
    h = 0.075
    states = InitialStates(
        {"block": grid_initial_states()}, {"block": (-h, -h, -np.pi)}, {"block": (h, h, np.pi)}
    )
    assert len(states) == 16
    np.testing.assert_array_equal(states.grid_offsets(5)["block"], grid_initial_states()[5])
    with pytest.raises(ValueError, match="outside"):
        states.grid_offsets(16)
    sampled = np.array([states.sample_offsets(s)["block"] for s in range(200)])
    assert np.abs(sampled[:, :2]).max() <= h and np.abs(sampled[:, 2]).max() <= np.pi
    assert sampled[:, 2].min() < -2.5 and sampled[:, 2].max() > 2.5  # any angle
    np.testing.assert_array_equal(states.sample_offsets(7)["block"], sampled[7])
    # products: every toy offset with every box offset, the first role slowest
    toy, box = np.arange(6.0).reshape(2, 3), 10 + np.arange(9.0).reshape(3, 3)
    prod = InitialStates.product(
        {"toy": toy, "box": box}, {"toy": (0, 0, 0), "box": (0, 0, 0)}, {"toy": (1, 1, 1), "box": (1, 1, 1)}
    )
    assert len(prod) == 6
    np.testing.assert_array_equal(prod.grid["toy"], toy[[0, 0, 0, 1, 1, 1]])
    np.testing.assert_array_equal(prod.grid["box"], box[[0, 1, 2, 0, 1, 2]])
    with pytest.raises(ValueError, match="same N"):
        InitialStates({"a": np.zeros((2, 3)), "b": np.zeros((3, 3))}, {"a": 0, "b": 0}, {"a": 0, "b": 0})


def test_offset_pose_rotates_about_the_object_origin_and_world_z():
    rest = planar_pose(0.5, 0.1, 0.3)
    np.testing.assert_allclose(
        offset_pose(rest, (0.02, -0.01, 0.4)), planar_pose(0.52, 0.09, 0.7), atol=1e-12
    )
    tilted = np.eye(4)
    tilted[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # lying on its side
    tilted[:3, 3] = (0.4, 0.0, 0.05)
    moved = offset_pose(tilted, (0.0, 0.0, np.pi / 2))
    np.testing.assert_allclose(moved[:3, 3], (0.4, 0.0, 0.05))  # origin unchanged, height kept
    np.testing.assert_allclose(
        moved[:3, :3], planar_pose(0, 0, np.pi / 2)[:3, :3] @ tilted[:3, :3], atol=1e-12
    )


def test_mean_squared_distance_matches_rigid_motion_formula():
    pts = sample_block_particles(TBlockShape(), 0.01).astype(np.float64)
    pts[:, :2] -= pts[:, :2].mean(0)  # rotate about the particles' own centroid
    t = np.array([0.03, -0.02])
    assert mean_squared_distance(transform_points(planar_pose(*t, 0.0), pts), pts) == pytest.approx(t @ t)
    th = np.deg2rad(40.0)
    r2 = np.mean(np.sum(pts[:, :2] ** 2, axis=1))
    moved = transform_points(planar_pose(0, 0, th), pts)
    assert mean_squared_distance(moved, pts) == pytest.approx(2 * (1 - np.cos(th)) * r2, rel=1e-9)


def test_success_needs_at_least_30_of_the_last_100_frames():
    win = SuccessWindow()
    for _ in range(70):
        win.update(False)
    for _ in range(29):
        assert not win.update(True)
    assert win.update(True)  # 30 hits
    for _ in range(70):  # the window slides: still the same 30 hits
        win.update(False)
    assert win.success
    win.update(False)  # the oldest hit leaves the window
    assert not win.success


def test_the_t_outline_agrees_with_its_boxes():
    """The T as twin data (an Outline polygon) answers as the T's boxes do: inside, nearest point,
    distance, and the footprint's polar moment (analytic for the T)."""
    shape = TBlockShape()
    outline = shape.outline()
    pts = np.random.default_rng(0).uniform([-0.08, -0.1, -0.01], [0.08, 0.06, 0.04], (4000, 3))
    np.testing.assert_array_equal(outline.contains(pts), shape.contains(pts))
    boxes = shape.boxes()
    rho2 = sum((hi[0] - lo[0]) * (hi[1] - lo[1]) * (((lo[:2] + hi[:2]) / 2) @ ((lo[:2] + hi[:2]) / 2)
               + ((hi[0] - lo[0]) ** 2 + (hi[1] - lo[1]) ** 2) / 12) for lo, hi in boxes) / outline.area
    assert outline.polar_radius2() == pytest.approx(rho2, rel=1e-12)
    assert outline.area == pytest.approx(0.12 * 0.03 + 0.03 * 0.09, rel=1e-12)
    for p in pts[:300, :2]:
        nearest = min((np.clip(p, lo[:2], hi[:2]) for lo, hi in boxes), key=lambda q: np.linalg.norm(p - q))
        np.testing.assert_allclose(outline.nearest(p), nearest, atol=1e-15)
        assert outline.distance(p) == pytest.approx(np.linalg.norm(p - nearest), abs=1e-15)
    small = outline.scaled(0.5)
    assert small.area == pytest.approx(outline.area / 4) and small.height == shape.height / 2


def test_outlines_are_validated():
    from twinbench.twin.shapes import Outline

    with pytest.raises(ValueError, match="counter-clockwise"):
        Outline(TBlockShape().outline_xy()[::-1], 0.03)
    with pytest.raises(ValueError, match=r"\(K, 2\)"):
        Outline(np.zeros((2, 2)), 0.03)
    with pytest.raises(ValueError, match="height"):
        Outline(TBlockShape().outline_xy(), 0.0)


def test_outline_contains_its_boundary_within_tol_and_nothing_beyond():
    outline = TBlockShape().outline()
    a = outline.polygon
    b = np.roll(a, -1, axis=0)
    t = np.linspace(0.0, 1.0, 7)[:, None, None]
    on_edges = (a[None] + t * (b - a)[None]).reshape(-1, 2)  # every edge, corners included
    assert outline.contains(on_edges, tol=1e-9).all()
    # pushed 1 mm out along each edge's outward normal (the polygon is counter-clockwise)
    e = b - a
    normal = np.c_[e[:, 1], -e[:, 0]] / np.linalg.norm(e, axis=1, keepdims=True)
    mid = 0.5 * (a + b)
    assert not outline.contains(mid + 1e-3 * normal, tol=1e-6).any()
    assert outline.contains(mid + 1e-7 * normal, tol=1e-6).all()
    assert outline.contains(mid - 1e-3 * normal, tol=1e-9).all()


def test_outline_contains_a_slanted_concave_polygon_as_brute_force_does():
    """A star (slanted edges, concave corners, a horizontal edge): `contains` against a per-point reference
    (ray crossing over every edge, distance to every edge), on random points and points within and beyond
    `tol` of the edges."""
    from twinbench.twin.shapes import Outline

    k = np.arange(10)
    radius = np.where(k % 2 == 0, 0.05, 0.02)
    star = np.c_[radius * np.cos(k * np.pi / 5), radius * np.sin(k * np.pi / 5)]
    star = np.r_[star[:3], [[0.0, star[2, 1]]], star[3:]]  # a horizontal edge
    outline = Outline(star, 0.02)
    rng = np.random.default_rng(3)
    a, b = star, np.roll(star, -1, axis=0)
    t = rng.uniform(0, 1, (400, 1))
    edge = rng.integers(0, len(a), 400)
    e = b[edge] - a[edge]
    normal = np.c_[e[:, 1], -e[:, 0]] / np.linalg.norm(e, axis=1, keepdims=True)
    off = rng.choice([-2e-6, -5e-7, 5e-7, 2e-6], (400, 1))
    pts = np.r_[rng.uniform(-0.06, 0.06, (3000, 2)), a[edge] + t * e + off * normal]
    tol = 1e-6

    def reference(p):
        crossings, dist = 0, np.inf
        for pa, pb in zip(a, b, strict=True):
            if (pa[1] > p[1]) != (pb[1] > p[1]):
                crossings += p[0] < pa[0] + (p[1] - pa[1]) * (pb[0] - pa[0]) / (pb[1] - pa[1])
            s = np.clip(np.dot(p - pa, pb - pa) / np.dot(pb - pa, pb - pa), 0.0, 1.0)
            dist = min(dist, np.linalg.norm(pa + s * (pb - pa) - p))
        return crossings % 2 == 1 or dist <= tol

    expected = np.array([reference(p) for p in pts])
    np.testing.assert_array_equal(outline.contains(pts, tol=tol), expected)
    assert expected[3000:].sum() == np.count_nonzero(off < 1e-6)  # inside or within tol: the first three
