"""Linear blend skinning: identity, rigid motion, and a bent rope."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from twinbench.gaussians.skinning import LabelRigidPoser, LBSSkinner, bind, skin
from twinbench.transforms import quat_to_matrix


def _blob(seed=0, n_particles=300, n_gauss=500):
    rng = np.random.default_rng(seed)
    particles = rng.uniform(-0.1, 0.1, size=(n_particles, 3))
    gauss = rng.uniform(-0.1, 0.1, size=(n_gauss, 3))
    quats = Rotation.random(n_gauss, random_state=seed).as_quat()[:, [3, 0, 1, 2]]
    return particles, gauss, quats


def test_binding_weights_and_neighbourhoods():
    particles, gauss, _ = _blob()
    b = bind(gauss, particles)
    assert b.indices.shape == (500, 16) and b.bone_neighbors.shape == (300, 8)
    np.testing.assert_allclose(b.weights.sum(axis=1), 1.0, atol=1e-6)
    # weights decrease with distance and the first index is the nearest particle
    d = np.linalg.norm(particles[b.indices] - gauss[:, None], axis=2)
    assert np.all(np.diff(d, axis=1) >= -1e-12) and np.all(np.diff(b.weights, axis=1) <= 1e-6)
    assert not np.any(b.bone_neighbors == np.arange(300)[:, None]), "a bone is not its own neighbour"
    with pytest.raises(ValueError, match="particles"):
        bind(gauss, particles[:, :2])


def test_unchanged_particles_leave_gaussians_unchanged():
    particles, gauss, quats = _blob(1)
    sk = LBSSkinner(bind(gauss, particles), gauss, quats)
    means, q = sk.update(particles)
    np.testing.assert_allclose(means.numpy(), gauss, atol=1e-6)
    np.testing.assert_allclose(q.numpy(), quats, atol=1e-5)


def test_rigid_motion_moves_gaussians_rigidly():
    particles, gauss, quats = _blob(2)
    rot = Rotation.from_rotvec([0.4, -0.7, 1.1]).as_matrix()
    t = np.array([0.3, -0.2, 0.5])
    sk = LBSSkinner(bind(gauss, particles), gauss, quats)
    means, q = sk.update(particles @ rot.T + t)
    np.testing.assert_allclose(means.numpy(), gauss @ rot.T + t, atol=1e-5)
    np.testing.assert_allclose(quat_to_matrix(q.numpy()), rot @ quat_to_matrix(quats), atol=1e-4)
    np.testing.assert_allclose(sk.bone_rotations.numpy(), np.broadcast_to(rot, (300, 3, 3)), atol=1e-4)


def test_bent_rope_bends_gaussians_smoothly():
    # a straight rope of 101 particles along x (1 cm spacing), Gaussians on and around it
    s = np.linspace(0.0, 1.0, 101)
    rope = np.c_[s, np.zeros_like(s), np.zeros_like(s)]
    rng = np.random.default_rng(3)
    u = rng.uniform(0.05, 0.95, 400)  # arclength parameter of each Gaussian
    offset = rng.uniform(-0.004, 0.004, size=(400, 2))  # within 4 mm of the axis
    gauss = np.c_[u, offset]
    quats = np.tile([1.0, 0, 0, 0], (400, 1))
    # bend it into a circular arc of radius R in the x-y plane (arclength preserved)
    radius = 1.0 / np.pi * 2  # quarter... 1 m of rope over pi/2 rad
    angle = s / radius
    bent = np.c_[radius * np.sin(angle), radius * (1 - np.cos(angle)), np.zeros_like(s)]
    binding = bind(gauss, rope)
    sk = LBSSkinner(binding, gauss, quats)
    means, q = sk.update(bent)
    moved = means.numpy()
    # Gaussians on the axis land on the arc: the bent centreline at their arclength, within 2 mm
    th = u / radius
    on_arc = np.c_[radius * np.sin(th), radius * (1 - np.cos(th)), np.zeros_like(u)]
    expected = (
        on_arc
        + offset[:, :1] * np.c_[-np.sin(th), np.cos(th), np.zeros_like(u)]
        + np.c_[0 * u, 0 * u, offset[:, 1]]
    )
    assert np.linalg.norm(moved - expected, axis=1).max() < 2e-3
    # no Gaussian moves more than its nearest bone plus what a rotation of the local 1-2 cm lever can add
    disp = np.linalg.norm(moved - gauss, axis=1)
    bone_disp = np.linalg.norm(bent - rope, axis=1)[binding.indices[:, 0]]
    lever = np.linalg.norm(gauss[:, None] - rope[binding.indices], axis=2).max(axis=1)
    bend_per_lever = lever / radius  # angle change across the binding neighbourhood
    assert np.all(disp <= bone_disp + lever * bend_per_lever * 2 + 1e-4)
    # smooth: Gaussians close at rest stay close (local stretch bounded)
    order = np.argsort(u)
    du_rest = np.linalg.norm(np.diff(gauss[order], axis=0), axis=1)
    du_now = np.linalg.norm(np.diff(moved[order], axis=0), axis=1)
    assert np.all(du_now <= 1.2 * du_rest + 1e-3)
    # Gaussian rotations follow the local tangent direction (about z by the arc angle)
    yaw = Rotation.from_quat(q.numpy()[:, [1, 2, 3, 0]]).as_rotvec()
    np.testing.assert_allclose(yaw[:, 2], th, atol=0.03)
    np.testing.assert_allclose(yaw[:, :2], 0, atol=1e-3)


def test_host_skin_and_rigid_device_variant(make_cloud):
    particles, gauss, quats = _blob(4, n_gauss=50)
    cloud = make_cloud(50, degree=1, seed=4)
    cloud.means[:] = gauss
    cloud.quats[:] = quats
    rot = Rotation.from_rotvec([0.0, 0.3, 0.2]).as_matrix()
    out = skin(bind(cloud.means, particles), cloud, particles @ rot.T)
    np.testing.assert_allclose(out.means, cloud.means @ rot.T, atol=1e-5)
    np.testing.assert_allclose(quat_to_matrix(out.quats), rot @ quat_to_matrix(cloud.quats), atol=1e-4)
    np.testing.assert_array_equal(out.sh, cloud.sh)
    np.testing.assert_array_equal(out.log_scales, cloud.log_scales)
    np.testing.assert_array_equal(out.logit_opacities, cloud.logit_opacities)
    transform = np.eye(4)
    transform[:3, :3] = rot
    transform[:3, 3] = [1, 2, 3]
    # rigid variant: one transform for all Gaussians = a single-label LabelRigidPoser
    posed = LabelRigidPoser(cloud, np.zeros(50, np.int32), 1).update(transform[None])
    m_out, q_out = posed.means, posed.quats
    ref = cloud.transform(transform)
    np.testing.assert_allclose(m_out.numpy(), ref.means, atol=1e-5)
    np.testing.assert_allclose(quat_to_matrix(q_out.numpy()), quat_to_matrix(ref.quats), atol=1e-5)


def test_skinned_device_gaussians_render_like_the_moved_cloud(make_cloud):
    """Device pipeline: LBS output -> DeviceGaussians.with_pose -> render, with no host round trip."""
    from twinbench.gaussians.camera import Camera
    from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud
    from twinbench.gaussians.render import render

    cloud = make_cloud(200, degree=0, seed=9, spread=0.1, anisotropic=True)
    particles = np.random.default_rng(9).uniform(-0.12, 0.12, size=(150, 3))
    motion = np.eye(4)
    motion[:3, :3] = Rotation.from_rotvec([0.1, 0.5, -0.2]).as_matrix()
    motion[:3, 3] = [0.05, 0.0, 0.02]
    dev = cloud.to_device("cpu")
    sk = LBSSkinner(bind(cloud.means, particles), cloud.means, cloud.quats)
    moved = dev.with_pose(*sk.update(particles @ motion[:3, :3].T + motion[:3, 3]))
    cam = Camera.look_at((0.5, 0.2, 0.3), (0, 0, 0), fx=50, width=48, height=40)
    expected = render(cloud.transform(motion), cam)
    assert np.abs(render(moved, cam).rgb - expected.rgb).max() < 2e-3
    # a scene-wide device cloud: static part + skinned part written in place into a slice
    static = make_cloud(50, degree=1, seed=10, spread=0.1)
    both = DeviceGaussians.concatenate([static.to_device("cpu"), dev])
    sk.update(
        particles @ motion[:3, :3].T + motion[:3, 3], out_means=both.means[50:], out_quats=both.quats[50:]
    )
    expected_both = render(GaussianCloud.concatenate([static, cloud.transform(motion)]), cam)
    assert np.abs(render(both, cam).rgb - expected_both.rgb).max() < 2e-3


def test_label_rigid_poser_matches_host_transform_with_sh(make_cloud):
    """Per-link rigid poses (robot links) on the device equal GaussianCloud.transform per subset, SH too."""
    from twinbench.gaussians.camera import Camera
    from twinbench.gaussians.cloud import GaussianCloud
    from twinbench.gaussians.render import render
    from twinbench.gaussians.skinning import LabelRigidPoser

    cloud = make_cloud(300, degree=3, seed=12, spread=0.2)
    labels = np.random.default_rng(12).integers(0, 3, 300)
    poses = np.tile(np.eye(4), (3, 1, 1))
    for i, rv in enumerate([[0.3, 0.0, 0.1], [0.0, -0.8, 0.4], [1.2, 0.5, -0.3]]):
        poses[i, :3, :3] = Rotation.from_rotvec(rv).as_matrix()
        poses[i, :3, 3] = [0.05 * i, -0.02, 0.01 * i]
    posed = LabelRigidPoser(cloud, labels).update(poses)
    for i in range(3):
        sel = np.flatnonzero(labels == i)
        ref = cloud.subset(sel).transform(poses[i])
        np.testing.assert_allclose(posed.means.numpy()[sel], ref.means, atol=1e-5)
        np.testing.assert_allclose(
            quat_to_matrix(posed.quats.numpy()[sel]), quat_to_matrix(ref.quats), atol=1e-5
        )
        np.testing.assert_allclose(posed.sh.numpy()[sel], ref.sh, atol=1e-5)
    # the posed device cloud renders like the host-posed one
    host = GaussianCloud.concatenate([cloud.subset(labels == i).transform(poses[i]) for i in range(3)])
    cam = Camera.look_at((0.6, 0.3, 0.3), (0, 0, 0), fx=50, width=40, height=32)
    dev_img = render(posed, cam).rgb
    host_img = render(host, cam).rgb
    assert np.abs(dev_img - host_img).max() < 2e-3
    with pytest.raises(ValueError, match="rotation"):
        LabelRigidPoser(cloud, labels).update(np.tile(np.diag([1.0, 1, -1, 1]), (3, 1, 1)))


def test_label_rigid_poser_writes_into_a_wider_out_buffer(make_cloud):
    """`out=` (a scene-wide buffer of higher SH degree): bands of `rest` are posed, the extra ones kept."""
    import warp as wp

    from twinbench.gaussians.cloud import DeviceGaussians

    cloud = make_cloud(40, degree=1, seed=13)
    wide = make_cloud(40, degree=3, seed=14).to_device("cpu")
    extra_before = wide.sh.numpy()[:, 4:].copy()
    pose = np.eye(4)
    pose[:3, :3] = Rotation.from_rotvec([0.2, -0.5, 0.9]).as_matrix()
    pose[:3, 3] = [0.1, 0.2, -0.3]
    poser = LabelRigidPoser(cloud, np.zeros(40, np.int32), 1, out=wide)
    assert poser.update(pose[None]) is wide
    ref = cloud.transform(pose)
    np.testing.assert_allclose(wide.means.numpy(), ref.means, atol=1e-5)
    np.testing.assert_allclose(quat_to_matrix(wide.quats.numpy()), quat_to_matrix(ref.quats), atol=1e-5)
    np.testing.assert_allclose(wide.sh.numpy()[:, :4], ref.sh, atol=1e-5)
    np.testing.assert_array_equal(wide.sh.numpy()[:, 4:], extra_before)
    narrow = DeviceGaussians(
        wide.means, wide.quats, wide.scales, wide.opacities, wp.zeros((40, 1), dtype=wp.vec3)
    )
    with pytest.raises(ValueError, match="SH"):
        LabelRigidPoser(cloud, np.zeros(40, np.int32), 1, out=narrow)


def test_lbs_copies_in_one_launch_equal_each_copy_alone():
    """update_many skins several particle sets (e.g. worlds) into one buffer; each copy is bit-identical to
    update on its particles alone, and copies land only where their starts say."""
    import warp as wp

    particles, gauss, quats = _blob(4, n_particles=80, n_gauss=120)
    sk = LBSSkinner(bind(gauss, particles), gauss, quats)
    rng = np.random.default_rng(4)
    sets = [particles + rng.normal(0, 0.01, particles.shape) for _ in range(3)]
    alone = [tuple(a.numpy().copy() for a in sk.update(p)) for p in sets]
    # particles of three "worlds" laid out with a gap; outputs reversed, after 7 untouched entries
    flat = np.concatenate([np.zeros((5, 3)), sets[0], sets[1], np.zeros((2, 3)), sets[2]]).astype(np.float32)
    pstarts = [5, 85, 167]
    ostarts = [7 + 240, 7 + 120, 7]
    means = wp.full(7 + 360, wp.vec3(9.0, 9.0, 9.0), dtype=wp.vec3)
    q = wp.zeros(7 + 360, dtype=wp.vec4)
    sk.update_many(wp.array(flat, dtype=wp.vec3), pstarts, means, q, ostarts)
    m_np, q_np = means.numpy(), q.numpy()
    assert np.all(m_np[:7] == 9.0)
    for c in range(3):
        np.testing.assert_array_equal(m_np[ostarts[c]: ostarts[c] + 120], alone[c][0])
        np.testing.assert_array_equal(q_np[ostarts[c]: ostarts[c] + 120], alone[c][1])
    with pytest.raises(ValueError, match="fit"):
        sk.update_many(wp.array(flat, dtype=wp.vec3), [200], means, q, [0])
    with pytest.raises(ValueError, match="starts"):
        sk.update_many(wp.array(flat, dtype=wp.vec3), [5, 85], means, q, [0])


def test_label_rigid_copies_in_one_launch_equal_each_copy_alone(make_cloud):
    from twinbench.gaussians.cloud import DeviceGaussians

    cloud = make_cloud(90, degree=2, seed=12, spread=0.1)
    labels = np.arange(90) % 3
    poser = LabelRigidPoser(cloud, labels, 3)
    rng = np.random.default_rng(12)
    sets = []
    for _ in range(2):
        t = np.tile(np.eye(4), (3, 1, 1))
        t[:, :3, :3] = Rotation.random(3, random_state=rng.integers(1 << 30)).as_matrix()
        t[:, :3, 3] = rng.normal(0, 0.1, (3, 3))
        sets.append(t)
    alone = []
    for t in sets:
        g = poser.update(t)
        alone.append([a.numpy().copy() for a in (g.means, g.quats, g.sh)])
    # a wider scene buffer (more SH coefficients): copy 1 first, then copy 0
    out = DeviceGaussians.concatenate([make_cloud(200, degree=3, seed=13).to_device("cpu")])
    poser.update_many(np.stack(sets), out, [105, 10])
    for c, first in ((0, 105), (1, 10)):
        for got, ref in zip((out.means, out.quats), alone[c][:2], strict=True):
            np.testing.assert_array_equal(got.numpy()[first: first + 90], ref)
        np.testing.assert_array_equal(out.sh.numpy()[first: first + 90, :9], alone[c][2])
    with pytest.raises(ValueError, match="transforms"):
        poser.update_many(sets[0], out, [0])


def test_posing_split_over_threads_equals_one_thread(make_cloud, monkeypatch):
    """Large poses split their launch over the render threads (`TWINBENCH_CPU_THREADS` of them, at most
    8); every Gaussian is posed alone, so the split result equals one thread's bit for bit, for rigid
    labels and LBS, and both copies of a two-copy pose land where their starts say."""
    import warp as wp

    from twinbench.gaussians import skinning
    from twinbench.gaussians.cloud import DeviceGaussians
    from twinbench.gaussians.threads import default_threads

    monkeypatch.setenv("TWINBENCH_CPU_THREADS", "3")
    assert default_threads() == 3
    monkeypatch.setenv("TWINBENCH_CPU_THREADS", "64")
    assert default_threads() == 8
    cloud = make_cloud(301, degree=3, seed=5, spread=0.1)
    poser = LabelRigidPoser(cloud, np.arange(301) % 4, 4)
    rng = np.random.default_rng(5)
    t = np.tile(np.eye(4), (2, 4, 1, 1))
    t[..., :3, :3] = Rotation.random(8, random_state=6).as_matrix().reshape(2, 4, 3, 3)
    t[..., :3, 3] = rng.normal(0, 0.1, (2, 4, 3))
    particles, gauss, quats = _blob(5, n_particles=60, n_gauss=301)
    sk = LBSSkinner(bind(gauss, particles), gauss, quats)
    moved = np.concatenate([particles, particles + rng.normal(0, 0.01, particles.shape)]).astype(np.float32)
    results = []
    for split_from in (10**9, 1):  # one thread, then every pose split
        monkeypatch.setattr(skinning, "_SPLIT_RIGID", split_from)
        monkeypatch.setattr(skinning, "_SPLIT_SKIN", split_from)
        out = DeviceGaussians.concatenate([make_cloud(602, degree=3, seed=7).to_device("cpu")])
        poser.update_many(t, out, [301, 0])
        means, q = wp.zeros(602, dtype=wp.vec3), wp.zeros(602, dtype=wp.vec4)
        sk.update_many(wp.array(moved, dtype=wp.vec3), [0, 60], means, q, [0, 301])
        results.append([a.numpy() for a in (out.means, out.quats, out.sh, means, q)])
    for one, split in zip(*results, strict=True):
        np.testing.assert_array_equal(split, one)
    np.testing.assert_array_equal(results[0][0][301:], poser.update(t[0]).means.numpy())
