"""Real spherical harmonics (degree 0..3) in the 3DGS convention, and their rotation."""

from __future__ import annotations

import numpy as np

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def sh_degree(num_coeffs: int) -> int:
    """SH degree of `num_coeffs` = (degree + 1)^2 coefficients per colour channel."""
    return int(round(np.sqrt(num_coeffs))) - 1


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """SH basis values (M, (degree+1)^2) at unit directions `dirs` (M, 3), 3DGS sign convention."""
    d = np.asarray(dirs, dtype=np.float64)
    x, y, z = d[:, 0], d[:, 1], d[:, 2]
    out = [np.full_like(x, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return np.stack(out, axis=1)


def eval_sh_colour(sh: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """Colour (M, 3) = max(0, 0.5 + sum_k sh[:, k] Y_k(dir)) for sh (M, K, 3) and unit dirs (M, 3)."""
    basis = sh_basis(dirs, sh_degree(sh.shape[1]))
    return np.maximum(np.einsum("mk,mkc->mc", basis, sh) + 0.5, 0.0)


def sh_rotation_matrices(rotation: np.ndarray, degree: int) -> list[np.ndarray]:
    """Per-band matrices D_l with f'(d) = f(R^T d): rotating a cloud by R maps coefficients c_l -> D_l c_l.

    Solved by least squares on sampled directions (each band is closed under rotation, so it is exact).
    """
    rot = np.asarray(rotation, dtype=np.float64)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    basis = sh_basis(dirs, degree)
    basis_rot = sh_basis(dirs @ rot, degree)  # rows: Y(R^T d)
    mats = []
    for band in range(degree + 1):
        sl = slice(band * band, (band + 1) ** 2)
        mats.append(np.linalg.lstsq(basis[:, sl], basis_rot[:, sl], rcond=None)[0])
    return mats


def rotate_sh(sh: np.ndarray, rotation: np.ndarray) -> np.ndarray:
    """SH coefficients (N, K, 3) of the colour field rotated by the 3x3 rotation `rotation`."""
    out = np.array(sh, dtype=np.float32, copy=True)
    for band, mat in enumerate(sh_rotation_matrices(rotation, sh_degree(sh.shape[1]))):
        if band == 0:
            continue
        sl = slice(band * band, (band + 1) ** 2)
        out[:, sl] = np.einsum("ij,njc->nic", mat, sh[:, sl]).astype(np.float32)
    return out
