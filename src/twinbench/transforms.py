"""Rigid-transform helpers shared by every package (numpy, float64, batched): quaternions wxyz,
rotation vectors, 4x4 poses."""

from __future__ import annotations

import numpy as np

__all__ = [
    "axis_angle_to_matrix",
    "invert_pose",
    "matrix_to_quat",
    "matrix_to_rotvec",
    "pose_matrix",
    "quat_multiply",
    "quat_to_matrix",
    "rotation_angle",
    "rotvec_to_matrix",
]


def quat_multiply(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product a * b of wxyz quaternions (broadcasting over leading axes)."""
    a = np.asarray(a)
    b = np.asarray(b)
    aw, ax, ay, az = np.moveaxis(a, -1, 0)
    bw, bx, by, bz = np.moveaxis(b, -1, 0)
    return np.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices (..., 3, 3) of wxyz quaternions (normalised first)."""
    q = np.asarray(q, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def matrix_to_quat(r: np.ndarray) -> np.ndarray:
    """Batched (..., 3, 3) rotations -> (..., 4) wxyz unit quaternions, w >= 0 (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    m = r.reshape(-1, 3, 3)
    tr = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    diag = np.stack([tr, m[:, 0, 0], m[:, 1, 1], m[:, 2, 2]], axis=1)
    k = np.argmax(diag, axis=1)
    q = np.empty((m.shape[0], 4))
    # Each branch computes the largest component first for numerical stability.
    for case in range(4):
        s = k == case
        if not np.any(s):
            continue
        a = m[s]
        if case == 0:
            t = np.sqrt(np.maximum(1.0 + tr[s], 1e-300)) * 2
            q[s] = np.stack(
                [
                    0.25 * t,
                    (a[:, 2, 1] - a[:, 1, 2]) / t,
                    (a[:, 0, 2] - a[:, 2, 0]) / t,
                    (a[:, 1, 0] - a[:, 0, 1]) / t,
                ],
                axis=1,
            )
        elif case == 1:
            t = np.sqrt(np.maximum(1.0 + a[:, 0, 0] - a[:, 1, 1] - a[:, 2, 2], 1e-300)) * 2
            q[s] = np.stack(
                [
                    (a[:, 2, 1] - a[:, 1, 2]) / t,
                    0.25 * t,
                    (a[:, 0, 1] + a[:, 1, 0]) / t,
                    (a[:, 0, 2] + a[:, 2, 0]) / t,
                ],
                axis=1,
            )
        elif case == 2:
            t = np.sqrt(np.maximum(1.0 + a[:, 1, 1] - a[:, 0, 0] - a[:, 2, 2], 1e-300)) * 2
            q[s] = np.stack(
                [
                    (a[:, 0, 2] - a[:, 2, 0]) / t,
                    (a[:, 0, 1] + a[:, 1, 0]) / t,
                    0.25 * t,
                    (a[:, 1, 2] + a[:, 2, 1]) / t,
                ],
                axis=1,
            )
        else:
            t = np.sqrt(np.maximum(1.0 + a[:, 2, 2] - a[:, 0, 0] - a[:, 1, 1], 1e-300)) * 2
            q[s] = np.stack(
                [
                    (a[:, 1, 0] - a[:, 0, 1]) / t,
                    (a[:, 0, 2] + a[:, 2, 0]) / t,
                    (a[:, 1, 2] + a[:, 2, 1]) / t,
                    0.25 * t,
                ],
                axis=1,
            )
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return q.reshape(r.shape[:-2] + (4,))


def axis_angle_to_matrix(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rodrigues: unit axis (3,) or (..., 3) and angles (...) -> (..., 3, 3)."""
    axis = np.asarray(axis, dtype=np.float64)
    angle = np.asarray(angle, dtype=np.float64)
    x, y, z = np.moveaxis(np.broadcast_to(axis, angle.shape + (3,)), -1, 0)
    c, s = np.cos(angle), np.sin(angle)
    t = 1.0 - c
    r = np.empty(angle.shape + (3, 3))
    r[..., 0, 0] = t * x * x + c
    r[..., 0, 1] = t * x * y - s * z
    r[..., 0, 2] = t * x * z + s * y
    r[..., 1, 0] = t * x * y + s * z
    r[..., 1, 1] = t * y * y + c
    r[..., 1, 2] = t * y * z - s * x
    r[..., 2, 0] = t * x * z - s * y
    r[..., 2, 1] = t * y * z + s * x
    r[..., 2, 2] = t * z * z + c
    return r


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """(..., 3) rotation vectors -> (..., 3, 3)."""
    v = np.asarray(v, dtype=np.float64)
    angle = np.linalg.norm(v, axis=-1)
    axis = v / np.maximum(angle, 1e-300)[..., None]
    axis = np.where(angle[..., None] > 1e-12, axis, np.array([0.0, 0.0, 1.0]))
    return axis_angle_to_matrix(axis, angle)


def matrix_to_rotvec(r: np.ndarray) -> np.ndarray:
    """(..., 3, 3) rotations -> (..., 3) rotation vectors (angle in [0, pi]), stable near 0 and pi."""
    q = matrix_to_quat(r)
    w = np.clip(q[..., 0], 0.0, 1.0)
    vec = q[..., 1:]
    s = np.linalg.norm(vec, axis=-1)
    angle = 2.0 * np.arctan2(s, w)
    scale = np.where(s > 1e-12, angle / np.maximum(s, 1e-300), 2.0)
    return vec * scale[..., None]


def pose_matrix(position: np.ndarray, quat_wxyz: np.ndarray) -> np.ndarray:
    """(..., 3) positions and (..., 4) wxyz quaternions -> (..., 4, 4) poses."""
    position = np.asarray(position, dtype=np.float64)
    rot = quat_to_matrix(quat_wxyz)
    shape = np.broadcast_shapes(position.shape[:-1], rot.shape[:-2])
    t = np.zeros(shape + (4, 4))
    t[..., :3, :3] = rot
    t[..., :3, 3] = position
    t[..., 3, 3] = 1.0
    return t


def invert_pose(t: np.ndarray) -> np.ndarray:
    """Inverse of (..., 4, 4) rigid transforms."""
    t = np.asarray(t, dtype=np.float64)
    out = np.zeros_like(t)
    rt = np.swapaxes(t[..., :3, :3], -1, -2)
    out[..., :3, :3] = rt
    out[..., :3, 3] = -np.einsum("...ij,...j->...i", rt, t[..., :3, 3])
    out[..., 3, 3] = 1.0
    return out


def rotation_angle(r_a: np.ndarray, r_b: np.ndarray) -> np.ndarray:
    """Geodesic angle (rad) between (..., 3, 3) rotations."""
    rel = np.einsum("...ji,...jk->...ik", r_a, r_b)
    return np.linalg.norm(matrix_to_rotvec(rel), axis=-1)


def planar_pose(x: float, y: float, theta: float) -> np.ndarray:
    """4x4 pose of a planar placement: translation (x, y, 0) and rotation theta (rad) about +z."""
    c, s = np.cos(theta), np.sin(theta)
    m = np.eye(4)
    m[:2, :2] = [[c, -s], [s, c]]
    m[:2, 3] = [x, y]
    return m


def transform_points(pose: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Apply a 4x4 rigid transform to (N, 3) points; with poses (..., 4, 4), each of them -> (..., N, 3)."""
    pose = np.asarray(pose, dtype=np.float64)
    rot_t = np.swapaxes(pose[..., :3, :3], -1, -2)
    return np.asarray(points, dtype=np.float64) @ rot_t + pose[..., None, :3, 3]


def fit_rigid_transform(src: np.ndarray, dst: np.ndarray) -> np.ndarray:
    """Least-squares rigid transform (4x4) mapping points src -> dst (Kabsch, reflection fixed)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    cs, cd = src.mean(0), dst.mean(0)
    u, _, vt = np.linalg.svd((src - cs).T @ (dst - cd))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    rot = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    out = np.eye(4)
    out[:3, :3] = rot
    out[:3, 3] = cd - rot @ cs
    return out
