"""Robot Gaussians: rigid per-link posing by FK, finger Gaussians follow the finger meshes, scan sampler."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from twinbench.gaussians.cloud import SH_C0, GaussianCloud
from twinbench.robot.gaussians import RobotGaussians, sample_robot_scan
from twinbench.transforms import quat_to_matrix


@pytest.fixture(scope="module")
def scan(arm):
    return sample_robot_scan(arm, spacing=0.01, seed=5)


def test_scan_covers_every_link_with_its_colour_and_lies_on_the_meshes(arm, scan):
    labelled = {arm.link_names[i] for i in np.unique(scan.link_index)}
    assert labelled == set(arm.visual_meshes)
    local = scan.local
    for name, mesh in arm.visual_meshes.items():
        sel = scan.link_index == arm.link_index(name)
        # count follows area / spacing^2
        assert sel.sum() == max(1, round(mesh.area / 0.01**2))
        # centres on the link's surface (link frame)
        _, dist, _ = trimesh.proximity.closest_point(mesh, local.means[sel].astype(np.float64))
        assert dist.max() < 1e-5
        # DC colour decodes to the URDF material colour
        np.testing.assert_allclose(
            0.5 + SH_C0 * local.sh[sel, 0], np.broadcast_to(arm.link_colors[name], (sel.sum(), 3)), atol=1e-6
        )
    # flat discs: the thin axis (local z) is the face normal
    z_axes = quat_to_matrix(local.quats)[:, :, 2]
    mesh = arm.visual_meshes["gripper_base"]
    sel = scan.link_index == arm.link_index("gripper_base")
    _, _, tri = trimesh.proximity.closest_point(mesh, local.means[sel].astype(np.float64))
    cos = np.abs(np.einsum("ij,ij->i", z_axes[sel], mesh.face_normals[tri]))
    assert np.median(cos) > 0.999
    assert np.all(np.exp(local.log_scales[:, 2]) < 0.2 * np.exp(local.log_scales[:, 0]))


def test_posed_moves_each_gaussian_exactly_with_its_link(arm, scan):
    rng = np.random.default_rng(0)
    q = arm.home_q + rng.uniform(-0.8, 0.8, arm.n_q)
    q[7] = 0.01
    cloud = scan.posed(q)
    assert isinstance(cloud, GaussianCloud) and len(cloud) == len(scan) and cloud.sh.shape[1] == 1
    t = arm.fk(q)
    local = scan.local
    # Brute-force reference, one Gaussian at a time with homogeneous 4x4 matrices.
    for i in rng.choice(len(scan), 300, replace=False):
        ti = t[scan.link_index[i]]
        expect = (ti @ np.r_[local.means[i], 1.0])[:3]
        np.testing.assert_allclose(cloud.means[i], expect, atol=2e-6)
        np.testing.assert_allclose(
            quat_to_matrix(cloud.quats[i]), ti[:3, :3] @ quat_to_matrix(local.quats[i]), atol=2e-6
        )
    np.testing.assert_array_equal(cloud.log_scales, local.log_scales)
    np.testing.assert_array_equal(cloud.logit_opacities, local.logit_opacities)


def test_links_move_rigidly_and_static_links_stay(arm, scan):
    q_a = arm.home_q
    q_b = arm.home_q.copy()
    q_b[3] += 0.5  # elbow (joint4): links 4..7 and the tool move, base..link3 do not
    a, b = scan.posed(q_a), scan.posed(q_b)
    moved_links = {"link4", "link5", "link6", "link7", "gripper_base", "left_finger", "right_finger"}
    for name in arm.visual_meshes:
        sel = np.nonzero(scan.link_index == arm.link_index(name))[0][:200]
        shift = np.linalg.norm(b.means[sel] - a.means[sel], axis=1)
        if name in moved_links:
            assert shift.min() > 1e-3, name
        else:
            assert shift.max() < 1e-6, name
        da = np.linalg.norm(a.means[sel, None] - a.means[None, sel], axis=-1)
        db = np.linalg.norm(b.means[sel, None] - b.means[None, sel], axis=-1)
        np.testing.assert_allclose(da, db, atol=5e-6)


def test_gripper_opening_moves_finger_gaussians_with_finger_meshes(arm, scan):
    q_open = arm.set_gripper(arm.home_q, 0.0)
    q_closed = arm.set_gripper(arm.home_q, 1.0)
    a, b = scan.posed(q_open), scan.posed(q_closed)
    for finger in ("left_finger", "right_finger"):
        sel = scan.link_index == arm.link_index(finger)
        va, vb = arm.contact_vertices(q_open, finger), arm.contact_vertices(q_closed, finger)
        mesh_shift = vb - va
        np.testing.assert_allclose(mesh_shift, np.broadcast_to(mesh_shift[0], mesh_shift.shape), atol=1e-12)
        assert np.linalg.norm(mesh_shift[0]) == pytest.approx(0.0425, abs=1e-12)
        np.testing.assert_allclose(
            b.means[sel] - a.means[sel], np.broadcast_to(mesh_shift[0], (sel.sum(), 3)), atol=2e-6
        )
        # the posed Gaussians lie on the posed contact mesh
        posed_mesh = trimesh.Trimesh(vb, arm.contact_faces(finger), process=False)
        _, dist, _ = trimesh.proximity.closest_point(posed_mesh, b.means[sel].astype(np.float64))
        assert dist.max() < 1e-5
    # other links do not move when only the gripper changes
    base = scan.link_index == arm.link_index("gripper_base")
    np.testing.assert_array_equal(a.means[base], b.means[base])


def test_from_world_round_trip_and_validation(arm, scan):
    q = arm.home_q + 0.3
    q[7] = 0.02
    world = scan.posed(q)
    again = RobotGaussians.from_world(arm, world, scan.link_index, q)
    np.testing.assert_allclose(again.means, scan.means, atol=2e-6)
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", again.quats, scan.quats)), 1.0, atol=1e-5)
    with pytest.raises(ValueError, match="link_index"):
        RobotGaussians(arm, scan.local, scan.link_index[:-1])
    with pytest.raises(ValueError, match="link_index"):
        RobotGaussians(arm, scan.local, np.full(len(scan), arm.n_links))


def test_sample_by_count(pusher_arm):
    g = sample_robot_scan(pusher_arm, n_gaussians=5000, seed=1)
    assert len(g) == 5000
    # split by area: floor(area share) per link (at least 1), the remainder to the largest link
    links = [name for name in pusher_arm.link_names if name in pusher_arm.visual_meshes]
    areas = np.array([pusher_arm.visual_meshes[name].area for name in links])
    counts = np.array([np.sum(g.link_index == pusher_arm.link_index(name)) for name in links])
    share = np.maximum(1, np.floor(areas / areas.sum() * 5000))
    big = np.argmax(areas)
    np.testing.assert_array_equal(np.delete(counts, big), np.delete(share, big))
    assert counts[big] >= share[big]
    with pytest.raises(ValueError, match="n_gaussians"):
        sample_robot_scan(pusher_arm, n_gaussians=3)
