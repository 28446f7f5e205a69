"""Inverse kinematics: batched Levenberg-Marquardt on the end-effector pose with joint limits.

The error is 6-D: position (m) and `rot_weight` x the world-frame rotation vector of R_target R^T (rad).
Each iteration solves (J^T J + lambda I) dq = J^T e per target, projects q + dq onto the joint limits,
and accepts the step only where the error decreased (lambda shrinks on success, grows on failure).
Targets that do not converge from the warm start are retried from random in-limit configurations
(`restarts`); the best solution is returned with `converged=False` when none meets the tolerances.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from twinbench.robot.model import RobotModel
from twinbench.transforms import matrix_to_rotvec, quat_to_matrix

DEFAULT_ROT_WEIGHT = 0.25  # metres of position error equivalent to one radian of rotation error


@dataclass
class IKResult:
    """Solutions q (B, n_q) (or (n_q,) for one target) with per-target convergence and final errors."""

    q: np.ndarray
    converged: np.ndarray  # bool (B,) or ()
    pos_err: np.ndarray  # metres
    rot_err: np.ndarray  # radians
    iterations: int


def pose_error(ee: np.ndarray, target: np.ndarray, rot_weight: float = 1.0,
               free_axis: np.ndarray | None = None) -> np.ndarray:
    """(B, 6) error [p_t - p, rot_weight * rotvec(R_t R^T)] between (B, 4, 4) poses.

    With `free_axis` (a unit vector in the end-effector frame) the rotation about that axis is free: the
    rotation part is the smallest rotation taking the end effector's axis (R a) onto the target's (R_t a),
    as a rotation vector (its angle is the angle between the two axes)."""
    ep = target[:, :3, 3] - ee[:, :3, 3]
    if free_axis is None:
        rel = target[:, :3, :3] @ np.swapaxes(ee[:, :3, :3], -1, -2)
        er = matrix_to_rotvec(rel)
    else:
        a, t = ee[:, :3, :3] @ free_axis, target[:, :3, :3] @ free_axis
        cross = np.cross(a, t)
        sin = np.linalg.norm(cross, axis=1)
        angle = np.arctan2(sin, np.einsum("bi,bi->b", a, t))
        # antiparallel axes (angle pi, no unique axis): turn about any axis normal to a
        normal = np.cross(a, np.where(np.abs(a[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
        axis = np.where(sin[:, None] > 1e-12, cross, normal)
        er = axis / np.linalg.norm(axis, axis=1, keepdims=True) * angle[:, None]
    return np.concatenate([ep, rot_weight * er], axis=1)


def _free_jacobian(ee: np.ndarray, jac: np.ndarray, free_axis: np.ndarray | None) -> np.ndarray:
    """The pose Jacobian (B, 6, n) with the angular rows' component along the end effector's free axis
    removed (turning about it changes nothing `pose_error` measures)."""
    if free_axis is None:
        return jac
    a = ee[:, :3, :3] @ free_axis
    out = jac.copy()
    out[:, 3:] -= a[:, :, None] * np.einsum("bi,bin->bn", a, jac[:, 3:])[:, None, :]
    return out


FULL_ORIENTATION_JOINTS = 6  # an arm with fewer joints cannot hold every orientation at every position


def free_yaw_axis(model: RobotModel, quat) -> np.ndarray | None:
    """For an arm of fewer than 6 joints (SO-100/101), the axis of its end-effector frame that points
    straight up or down when the end effector is at orientation `quat` (wxyz): the rotation about it, a
    turn about the vertical, is left free when such a tool points down (a pusher, a gripper reaching
    down); None for arms that can hold the whole orientation."""
    if model.arm_q_indices.size >= FULL_ORIENTATION_JOINTS:
        return None
    return quat_to_matrix(np.asarray(quat, dtype=np.float64)).T @ np.array([0.0, 0.0, 1.0])


def weighted_error(pos_err, rot_err, rot_weight: float = DEFAULT_ROT_WEIGHT):
    """Squared weighted pose error |p_err|^2 + (rot_weight |r_err|)^2: how solutions are ranked."""
    return pos_err**2 + (rot_weight * rot_err) ** 2


def _check_targets(target: np.ndarray) -> np.ndarray:
    t = np.asarray(target, dtype=np.float64)
    if t.shape[-2:] != (4, 4) or t.ndim not in (2, 3):
        raise ValueError(f"target: expected a (4, 4) pose or (B, 4, 4) poses, got shape {t.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("target: contains NaN or inf")
    r = t[..., :3, :3]
    ortho = np.abs(np.swapaxes(r, -1, -2) @ r - np.eye(3)).max()
    if ortho > 1e-4 or np.any(np.linalg.det(r) < 0):
        raise ValueError("target: rotation part is not a proper rotation matrix (R^T R != I or det < 0)")
    return t


def random_configurations(model: RobotModel, n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, n_q) configurations uniform within the limits (unbounded joints drawn in [-pi, pi])."""
    lo = np.maximum(model.lower, -np.pi)
    hi = np.minimum(model.upper, np.pi)
    return rng.uniform(lo, hi, size=(n, model.n_q))


def _lm(
    model: RobotModel,
    target: np.ndarray,
    q: np.ndarray,
    max_iters: int,
    pos_tol: float,
    rot_tol: float,
    rot_weight: float,
    free_axis: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Run LM on all rows; returns q, position error, rotation error, iterations used."""
    arm = model.arm_q_indices
    lo, hi = model.lower[arm], model.upper[arm]
    b, n = q.shape[0], arm.size
    lam = np.full(b, 1e-2)
    ee, jac = model.ee_pose_and_jacobian(q)
    jac = _free_jacobian(ee, jac, free_axis)
    err = pose_error(ee, target, rot_weight, free_axis)
    cost = np.einsum("bi,bi->b", err, err)
    w = np.array([1.0, 1.0, 1.0, rot_weight, rot_weight, rot_weight])
    eye = np.eye(n)
    it = 0
    for _ in range(max_iters):
        pe = np.linalg.norm(err[:, :3], axis=1)
        re = np.linalg.norm(err[:, 3:], axis=1) / rot_weight
        active = (pe > pos_tol) | (re > rot_tol)
        active &= lam < 1e6
        if not np.any(active):
            break
        it += 1
        idx = np.nonzero(active)[0]
        ja = jac[idx] * w[None, :, None]
        jt = np.swapaxes(ja, 1, 2)
        a = jt @ ja + lam[idx, None, None] * eye
        g = np.einsum("bij,bj->bi", jt, err[idx])
        dq = np.linalg.solve(a, g[..., None])[..., 0]
        qc = q[idx].copy()
        qc[:, arm] = np.clip(qc[:, arm] + dq, lo, hi)
        ee_c, jac_c = model.ee_pose_and_jacobian(qc)
        jac_c = _free_jacobian(ee_c, jac_c, free_axis)
        err_c = pose_error(ee_c, target[idx], rot_weight, free_axis)
        cost_c = np.einsum("bi,bi->b", err_c, err_c)
        ok = (cost_c < cost[idx]) & np.all(np.isfinite(qc), axis=1) & np.isfinite(cost_c)
        acc = idx[ok]
        q[acc], jac[acc], err[acc], cost[acc] = qc[ok], jac_c[ok], err_c[ok], cost_c[ok]
        lam[acc] = np.maximum(lam[acc] / 3.0, 1e-7)
        rej = idx[~ok]
        lam[rej] *= 5.0
    pe = np.linalg.norm(err[:, :3], axis=1)
    re = np.linalg.norm(err[:, 3:], axis=1) / rot_weight
    return q, pe, re, it


def solve_ik(
    model: RobotModel,
    target: np.ndarray,
    q_init: np.ndarray | None = None,
    *,
    max_iters: int = 150,
    pos_tol: float = 1e-5,
    rot_tol: float = 1e-4,
    rot_weight: float = DEFAULT_ROT_WEIGHT,
    restarts: int = 16,
    seed: int = 0,
    free_axis=None,
) -> IKResult:
    """Solve for configurations whose end-effector pose matches `target` ((4, 4) or (B, 4, 4)).

    `q_init` ((n_q,) or (B, n_q), default `model.home_q`) warm-starts the solve; non-arm joints (gripper)
    are copied from it. Never returns NaN: unreachable targets give the closest solution found
    (smallest weighted error) with `converged=False`. `free_axis` (3 numbers, an axis of the end-effector
    frame): the rotation about it is left free (a 5-joint arm holding a symmetric tool along it); the
    rotation error is then the angle between that axis and the target's.
    """
    if free_axis is not None:
        free_axis = np.asarray(free_axis, dtype=np.float64).reshape(3)
        if not np.all(np.isfinite(free_axis)) or not np.linalg.norm(free_axis) > 1e-9:
            raise ValueError(f"free_axis: expected a nonzero 3-vector, got {free_axis.tolist()}")
        free_axis = free_axis / np.linalg.norm(free_axis)
    if model.arm_q_indices.size == 0:
        raise ValueError(
            f"model {model.name!r}: no actuated joint between the root and ee_link {model.ee_link!r}"
        )
    t = _check_targets(target)
    single = t.ndim == 2
    t = t[None] if single else t
    b = t.shape[0]
    q0 = model.home_q if q_init is None else model.check_q(q_init, "q_init")
    q0 = np.broadcast_to(q0, (b, model.n_q)).copy() if q0.ndim == 1 or q0.shape[0] == 1 else q0.copy()
    if q0.shape[0] != b:
        raise ValueError(f"q_init: batch {q0.shape[0]} does not match target batch {b}")
    q0 = model.clip_q(q0)
    q, pe, re, iters = _lm(model, t, q0, max_iters, pos_tol, rot_tol, rot_weight, free_axis)
    conv = (pe <= pos_tol) & (re <= rot_tol)
    rng = np.random.default_rng(seed)
    for _ in range(restarts):
        todo = np.nonzero(~conv)[0]
        if todo.size == 0:
            break
        qr = q0[todo].copy()
        qr[:, model.arm_q_indices] = random_configurations(model, todo.size, rng)[:, model.arm_q_indices]
        qn, pen, ren, _ = _lm(model, t[todo], qr, max_iters, pos_tol, rot_tol, rot_weight, free_axis)
        better = weighted_error(pen, ren, rot_weight) < weighted_error(pe[todo], re[todo], rot_weight)
        sel = todo[better]
        q[sel], pe[sel], re[sel] = qn[better], pen[better], ren[better]
        conv = (pe <= pos_tol) & (re <= rot_tol)
    if single:
        return IKResult(q[0], conv[0], pe[0], re[0], iters)
    return IKResult(q, conv, pe, re, iters)
