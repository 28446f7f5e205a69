"""Helpers for the gaussians tests: random clouds and a brute-force NumPy reference renderer."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.sh import eval_sh_colour
from twinbench.transforms import quat_to_matrix


def random_cloud(
    n: int,
    *,
    degree: int = 0,
    seed: int = 0,
    center=(0.0, 0.0, 0.0),
    spread: float = 0.3,
    log_scale=(-4.0, -2.5),
    anisotropic: bool = False,
) -> GaussianCloud:
    rng = np.random.default_rng(seed)
    means = np.asarray(center) + rng.uniform(-spread, spread, size=(n, 3))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    log_scales = rng.uniform(*log_scale, size=(n, 3))
    if anisotropic:
        # thin discs (one axis ~30x shorter) and, for a third of them, needles (two short axes)
        axis = rng.integers(0, 3, size=n)
        log_scales[np.arange(n), axis] -= 3.5
        needles = rng.random(n) < 1 / 3
        log_scales[np.flatnonzero(needles), (axis[needles] + 1) % 3] -= 3.5
    k = (degree + 1) ** 2
    sh = rng.normal(scale=0.4, size=(n, k, 3))
    sh[:, 1:] *= 0.5
    return GaussianCloud(means, quats, log_scales, rng.uniform(-2.0, 4.0, size=n), sh)


def reference_render(cloud: GaussianCloud, cam: Camera, background=(0.0, 0.0, 0.0)):
    """Every pixel composites every Gaussian (float64, depth-sorted), with the renderer's stated rules."""
    w2c = cam.world_to_cam
    p = cloud.means.astype(np.float64) @ w2c[:3, :3].T + w2c[:3, 3]
    z = p[:, 2]
    op = 1.0 / (1.0 + np.exp(-cloud.logit_opacities.astype(np.float64)))
    rot = quat_to_matrix(cloud.quats)
    m = rot * np.exp(cloud.log_scales.astype(np.float64))[:, None, :]
    cov_c = w2c[:3, :3] @ (m @ m.transpose(0, 2, 1)) @ w2c[:3, :3].T
    tan_x, tan_y = 0.5 * cam.width / cam.fx, 0.5 * cam.height / cam.fy
    zs = np.where(z > 0, z, 1.0)
    tx = (
        np.clip(p[:, 0] / zs, -(cam.cx / cam.fx + 0.3 * tan_x), (cam.width - cam.cx) / cam.fx + 0.3 * tan_x)
        * zs
    )
    ty = (
        np.clip(p[:, 1] / zs, -(cam.cy / cam.fy + 0.3 * tan_y), (cam.height - cam.cy) / cam.fy + 0.3 * tan_y)
        * zs
    )
    jac = np.zeros((len(z), 2, 3))
    jac[:, 0, 0] = cam.fx / zs
    jac[:, 0, 2] = -cam.fx * tx / zs**2
    jac[:, 1, 1] = cam.fy / zs
    jac[:, 1, 2] = -cam.fy * ty / zs**2
    cov2 = jac @ cov_c @ jac.transpose(0, 2, 1) + 0.3 * np.eye(2)
    inv = np.linalg.inv(cov2)
    uv = np.stack([cam.fx * p[:, 0] / zs + cam.cx, cam.fy * p[:, 1] / zs + cam.cy], 1)
    dirs = cloud.means - cam.position
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    colour = eval_sh_colour(cloud.sh.astype(np.float64), dirs)
    keep = np.flatnonzero((z >= 0.01) & (op >= 1 / 255))
    keep = keep[np.argsort(z[keep], kind="stable")]
    jj, ii = np.mgrid[0 : cam.height, 0 : cam.width]
    pix = np.stack([ii.ravel() + 0.5, jj.ravel() + 0.5], 1)
    T = np.ones(len(pix))
    done = np.zeros(len(pix), bool)
    rgb = np.zeros((len(pix), 3))
    dep = np.zeros(len(pix))
    for g in keep:
        d = pix - uv[g]
        d2 = np.einsum("pi,ij,pj->p", d, inv[g], d)
        alpha = np.minimum(0.99, op[g] * np.exp(-0.5 * d2))
        ok = (~done) & (alpha >= 1 / 255)
        test_t = T * (1 - alpha)
        stop = ok & (test_t < 1e-4)
        done |= stop
        ok &= ~stop
        wgt = np.where(ok, alpha * T, 0.0)
        rgb += wgt[:, None] * colour[g]
        dep += wgt * z[g]
        T = np.where(ok, test_t, T)
    alpha_img = 1 - T
    rgb = np.clip(rgb + T[:, None] * np.asarray(background), 0, 1)
    dep = np.where(alpha_img > 0, dep / np.where(alpha_img > 0, alpha_img, 1), 0)
    shape = (cam.height, cam.width)
    return rgb.reshape(*shape, 3), dep.reshape(shape), alpha_img.reshape(shape)


@pytest.fixture
def make_cloud():
    return random_cloud


@pytest.fixture
def ref_render():
    return reference_render
