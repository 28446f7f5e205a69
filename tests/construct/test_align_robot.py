"""align-robot: a synthetic robot scan, moved by a hidden similarity transform with 2 mm noise and 20 %
floaters, is registered back to its URDF (< 3 mm, < 0.5 deg) and labelled by link (>= 98 %, fingers too)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from twinbench.construct.align_robot import (
    RegistrationParams,
    fit_similarity,
    fpfh_features,
    gaussian_normals,
    register_robot,
    sample_robot_surface,
)
from twinbench.robot.builtin import load_builtin_arm
from twinbench.robot.gaussians import sample_robot_scan
from twinbench.transforms import rotation_angle, rotvec_to_matrix

NOISE = 0.002
OUTLIER_FRACTION = 0.2


def _hidden(model, q, points, link_index) -> np.ndarray:
    """Scan points whose link is not defined by what a camera sees: inside another link's solid, or
    within 0.5 mm of another link's surface (coincident faces where two links touch). The built-in arm's
    links are overlapping primitives, so about a third of its surface sample is hidden; a real scan holds
    only the visible surface."""
    poses = model.fk(q)
    hidden = np.zeros(len(points), bool)
    for name, mesh in model.visual_meshes.items():
        li = model.link_index(name)
        posed = mesh.copy()
        posed.apply_transform(poses[li])
        for part in posed.split(only_watertight=False):
            lo, hi = part.bounds
            cand = np.flatnonzero((link_index != li) & np.all((points > lo - 1e-3) & (points < hi + 1e-3), 1))
            if len(cand):
                hidden[cand[part.contains(points[cand])]] = True
                _, dist, _ = trimesh.proximity.closest_point(part, points[cand])
                hidden[cand[dist < 5e-4]] = True
    return hidden


def _scenario(model, q, seed: int, scale: float | None, spacing: float = 0.006):
    """World-frame scan of `model` at q, moved by a random transform (rotation <= 45 deg, translation <= 30
    cm, optional scale), with noise and uniform floaters; returns everything the checks need."""
    rng = np.random.default_rng(seed)
    scan = sample_robot_scan(model, spacing=spacing, seed=seed + 100)
    world = scan.posed(q)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.radians(rng.uniform(30.0, 45.0))
    s = 1.0 if scale is None else scale
    true = np.eye(4)  # world -> scan
    true[:3, :3] = s * rotvec_to_matrix(axis * angle)
    true[:3, 3] = rng.uniform(-1.0, 1.0, 3) * 0.3 / np.sqrt(3)
    pts = world.means.astype(np.float64) @ true[:3, :3].T + true[:3, 3]
    pts += rng.normal(scale=NOISE * s, size=pts.shape)
    n_out = int(round(OUTLIER_FRACTION / (1 - OUTLIER_FRACTION) * len(pts)))
    lo, hi = pts.min(0) - 0.1, pts.max(0) + 0.1
    scan_pts = np.concatenate([pts, rng.uniform(lo, hi, (n_out, 3))])
    normals = np.concatenate([gaussian_normals(world) @ true[:3, :3].T / s, np.full((n_out, 3), np.nan)])
    return scan, world, true, scan_pts, normals


def _check(model, q, scan, world, true, result, n_robot):
    err = result.transform @ true  # identity when exact
    s_err = np.cbrt(np.linalg.det(err[:3, :3]))
    assert abs(s_err - 1.0) < 2e-3
    assert np.degrees(rotation_angle(err[:3, :3] / s_err, np.eye(3))) < 0.5
    p = world.means.astype(np.float64)
    disp = np.linalg.norm(p @ err[:3, :3].T + err[:3, 3] - p, axis=1)
    assert disp.max() < 0.003, f"max point error {disp.max() * 1e3:.2f} mm"
    labels = result.labels[:n_robot]
    visible = ~_hidden(model, q, p, scan.link_index)
    ok = labels == scan.link_index
    assert ok[visible].mean() >= 0.98, f"label accuracy {ok[visible].mean():.4f}"
    return ok, visible


@pytest.fixture(scope="module")
def gripper_arm():
    return load_builtin_arm("gripper")


@pytest.mark.parametrize("seed, scale", [(1, None), (2, 0.83), (3, 1.17)])
def test_builtin_arm_scan_is_registered_and_labelled(gripper_arm, seed, scale):
    model = gripper_arm
    q = model.set_gripper(model.home_q.copy(), 0.4)
    q[:7] += np.random.default_rng(seed).uniform(-0.3, 0.3, 7)
    scan, world, true, pts, normals = _scenario(model, q, seed, scale)
    params = RegistrationParams(estimate_scale=scale is not None, label_points_per_link=10000)
    result = register_robot(pts, model, q, params, scan_normals=normals)
    ok, visible = _check(model, q, scan, world, true, result, len(world))
    for finger in ("left_finger", "right_finger"):
        li = model.link_index(finger)
        m = (scan.link_index == li) & visible
        assert m.sum() > 50 and ok[m].mean() >= 0.98, finger
    # floaters: most are far from every link and are not counted by the report
    far = result.distances[len(world):] > 0.01
    assert far.mean() > 0.8
    rep = result.report(max_distance=0.01)
    assert rep["per_link"]["left_finger"] > 50 and 0.7 < rep["fitness"] <= 1.0
    assert rep["rmse_m"] < 2 * NOISE * 1.5


def test_real_xarm7_scan_is_registered_and_labelled():
    from twinbench.robot.builtin import load_xarm7

    try:
        model = load_xarm7()
    except ModuleNotFoundError as exc:
        pytest.skip(str(exc))
    q = model.home_q.copy() + np.random.default_rng(7).uniform(-0.3, 0.3, model.n_q)
    q = model.clip_q(q)
    scan, world, true, pts, normals = _scenario(model, q, 7, 1.1)
    params = RegistrationParams(estimate_scale=True, label_points_per_link=10000)
    result = register_robot(pts, model, q, params, scan_normals=normals)
    _check(model, q, scan, world, true, result, len(world))


@pytest.mark.parametrize("seed, scale", [(4, 3.7), (5, 0.05)])
def test_a_scan_in_any_unit_and_orientation_registers_with_scale(gripper_arm, seed, scale):
    """COLMAP-like scans: any unit (the first scale estimate comes from the clouds' spreads), any
    orientation (here a further 90 deg about x on top of the random one: y up)."""
    model = gripper_arm
    q = model.home_q
    scan, world, true, pts, normals = _scenario(model, q, seed, scale)
    flip = np.eye(4)
    flip[:3, :3] = rotvec_to_matrix(np.array([np.pi / 2, 0.0, 0.0]))
    pts, normals, true = pts @ flip[:3, :3].T, normals @ flip[:3, :3].T, flip @ true
    params = RegistrationParams(estimate_scale=True, label_points_per_link=10000)
    result = register_robot(pts, model, q, params, scan_normals=normals)
    _check(model, q, scan, world, true, result, len(world))


def test_a_scan_not_in_metres_is_refused_without_scale_and_nothing_is_written(gripper_arm, tmp_path):
    from twinbench.construct.align_robot import align_robot_files
    from twinbench.gaussians.io import save_gaussians

    scan = sample_robot_scan(gripper_arm, spacing=0.008, seed=3)
    cloud = scan.posed(gripper_arm.home_q)
    big = np.diag([3.7, 3.7, 3.7, 1.0])
    save_gaussians(cloud.transform(big), tmp_path / "robot.ply")
    with pytest.raises(ValueError, match=r"robot\.ply: after registration .* % of the robot's Gaussians .* "
                                         r"add --scale"):
        align_robot_files(tmp_path / "robot.ply", tmp_path / "out")
    assert not (tmp_path / "out").exists()
    rep = align_robot_files(tmp_path / "robot.ply", tmp_path / "out",
                            params=RegistrationParams(estimate_scale=True))
    assert abs(rep["scale"] * 3.7 - 1.0) < 2e-3 and rep["fitness"] > 0.95
    # a scan in units of 1 / 100 m spans under 4 voxels of 0.012 m: with --scale its extent is not held
    # against it
    save_gaussians(cloud.transform(np.diag([0.01, 0.01, 0.01, 1.0])), tmp_path / "tiny.ply")
    rep = align_robot_files(tmp_path / "tiny.ply", tmp_path / "out2",
                            params=RegistrationParams(estimate_scale=True))
    assert abs(rep["scale"] * 0.01 - 1.0) < 2e-3 and rep["fitness"] > 0.95


def test_registration_without_scale_rejects_nothing_it_should_keep(gripper_arm):
    """A scan already in the world frame (identity) is kept there: the global stage does not wander."""
    model = gripper_arm
    q = model.home_q
    scan = sample_robot_scan(model, spacing=0.008, seed=3)
    pts = scan.posed(q).means.astype(np.float64)
    result = register_robot(pts, model, q, RegistrationParams(label_points_per_link=4000))
    assert np.linalg.norm(result.transform[:3, 3]) < 1e-3
    assert np.degrees(rotation_angle(result.transform[:3, :3], np.eye(3))) < 0.1


def test_fit_similarity_recovers_a_known_similarity_batched():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(5, 20, 3))
    t = np.zeros((5, 4, 4))
    for b in range(5):
        t[b, :3, :3] = rng.uniform(0.5, 2) * rotvec_to_matrix(rng.normal(size=3))
        t[b, :3, 3] = rng.normal(size=3)
        t[b, 3, 3] = 1
    dst = np.einsum("bij,bnj->bni", t[:, :3, :3], src) + t[:, None, :3, 3]
    np.testing.assert_allclose(fit_similarity(src, dst), t, atol=1e-10)
    rigid = fit_similarity(src[0], src[0] @ t[0, :3, :3].T / np.cbrt(np.linalg.det(t[0, :3, :3])),
                           with_scale=False)
    assert np.isclose(np.linalg.det(rigid[:3, :3]), 1.0)


def test_fpfh_is_invariant_to_rigid_motion():
    mesh = trimesh.creation.torus(major_radius=0.1, minor_radius=0.03)
    pts, faces = trimesh.sample.sample_surface(mesh, 3000, seed=0)
    nrm = mesh.face_normals[faces]
    rot = rotvec_to_matrix(np.array([0.3, -0.5, 0.9]))
    f0 = fpfh_features(pts, nrm)
    f1 = fpfh_features(pts @ rot.T + 1.0, -(nrm @ rot.T))  # normal signs flipped too
    assert f0.shape == (len(pts), 33)
    # equal up to round-off moving a value across a bin edge (rare)
    assert np.mean(np.abs(f0 - f1) > 1e-6) < 0.01
    # and the feature tells different geometry apart: the torus' inside vs outside rim
    r = np.linalg.norm(pts[:, :2], axis=1)
    assert np.linalg.norm(f0[r < 0.08].mean(0) - f0[r > 0.12].mean(0)) > 5.0


def test_sample_robot_surface_labels_points_by_link(gripper_arm):
    s = sample_robot_surface(gripper_arm, points_per_link=500)
    links = sorted(set(s.link_index.tolist()))
    assert [gripper_arm.link_names[i] for i in links] == [n for n in gripper_arm.link_names
                                                         if n in gripper_arm.visual_meshes]
    assert np.allclose(np.linalg.norm(s.normals, axis=1), 1.0)
    with pytest.raises(ValueError, match="points_per_link"):
        sample_robot_surface(gripper_arm, points_per_link=0)
