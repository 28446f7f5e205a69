"""Batched rotation helpers against scipy's Rotation (reference), including angles near 0 and pi."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from twinbench.transforms import (
    invert_pose,
    matrix_to_quat,
    matrix_to_rotvec,
    pose_matrix,
    rotation_angle,
    rotvec_to_matrix,
)


def _rotvecs(rng, n=500):
    axes = rng.normal(size=(n, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = np.concatenate(
        [rng.uniform(0, np.pi, n - 6), [0.0, 1e-9, 1e-5, np.pi - 1e-9, np.pi - 1e-5, np.pi]]
    )
    return axes * angles[:, None]


def test_matrix_quat_rotvec_match_scipy():
    rng = np.random.default_rng(0)
    rv = _rotvecs(rng)
    ref = Rotation.from_rotvec(rv)
    mats = rotvec_to_matrix(rv)
    np.testing.assert_allclose(mats, ref.as_matrix(), atol=1e-12)
    q = matrix_to_quat(mats)
    q_ref = ref.as_quat()[:, [3, 0, 1, 2]]  # scipy is xyzw
    q_ref *= np.where(q_ref[:, :1] < 0, -1, 1)
    # near pi both signs of a w ~ 0 quaternion are valid: compare up to sign
    np.testing.assert_allclose(np.abs(np.einsum("ij,ij->i", q, q_ref)), 1.0, atol=1e-12)
    assert np.all(q[:, 0] >= 0)
    back = matrix_to_rotvec(mats)
    np.testing.assert_allclose(rotvec_to_matrix(back), mats, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(back, axis=1), np.linalg.norm(rv, axis=1), atol=1e-8)
    np.testing.assert_allclose(matrix_to_quat(mats.reshape(10, 50, 3, 3)).reshape(-1, 4), q)


def test_pose_inverse_and_angle():
    rng = np.random.default_rng(1)
    rv = _rotvecs(rng, 50)
    t = pose_matrix(rng.normal(size=(50, 3)), matrix_to_quat(rotvec_to_matrix(rv)))
    np.testing.assert_allclose(t @ invert_pose(t), np.broadcast_to(np.eye(4), t.shape), atol=1e-12)
    np.testing.assert_allclose(rotation_angle(np.eye(3), t[:, :3, :3]), np.linalg.norm(rv, axis=1), atol=1e-8)


def test_planar_pose_and_transform_points():
    from twinbench.transforms import planar_pose, transform_points

    pose = planar_pose(0.5, -0.2, np.pi / 2)
    np.testing.assert_allclose(transform_points(pose, [[1.0, 0.0, 0.3]]), [[0.5, 0.8, 0.3]], atol=1e-12)
    np.testing.assert_allclose(pose[:3, :3] @ pose[:3, :3].T, np.eye(3), atol=1e-12)


def test_fit_rigid_transform_recovers_a_known_pose():
    from twinbench.transforms import fit_rigid_transform

    rng = np.random.default_rng(1)
    src = rng.normal(size=(40, 3))
    angle = 2.5
    truth = np.eye(4)
    truth[:3, :3] = [[np.cos(angle), -np.sin(angle), 0], [np.sin(angle), np.cos(angle), 0], [0, 0, 1]]
    truth[:3, 3] = [0.3, -0.2, 0.05]
    dst = src @ truth[:3, :3].T + truth[:3, 3]
    np.testing.assert_allclose(fit_rigid_transform(src, dst), truth, atol=1e-12)


def test_transform_points_with_a_pose_per_frame():
    from twinbench.transforms import planar_pose, transform_points

    poses = np.stack([planar_pose(0.1 * k, -0.2, 0.3 * k) for k in range(4)])
    pts = np.array([[1.0, 0.0, 0.3], [0.0, 2.0, -1.0]])
    out = transform_points(poses, pts)
    assert out.shape == (4, 2, 3)
    for k in range(4):  # each frame as the single-pose form gives it
        np.testing.assert_array_equal(out[k], transform_points(poses[k], pts))
    np.testing.assert_allclose(out[2, 0], [0.2 + np.cos(0.6), -0.2 + np.sin(0.6), 0.3], atol=1e-12)
