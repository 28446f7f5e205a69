"""The brute-force NumPy reference renderer (backend "reference"): every pixel composites every Gaussian in
float64, with the rules of render_rules, one stage per function so each can be checked on its own. Slow
(pixels x Gaussians): for tests and small images, the yardstick the fast backends are measured against."""

from __future__ import annotations

import numpy as np

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud
from twinbench.gaussians.render_rules import ALPHA_MAX, ALPHA_MIN, LOW_PASS, NEAR, T_MIN, RenderOutput
from twinbench.gaussians.sh import eval_sh_colour
from twinbench.transforms import quat_to_matrix


def _host(cloud: GaussianCloud | DeviceGaussians) -> tuple[np.ndarray, ...]:
    """(means, quats, scales, opacities, sh) as host float64 arrays (scales linear, opacities 0..1)."""
    if isinstance(cloud, DeviceGaussians):
        return tuple(a.numpy().astype(np.float64) for a in
                     (cloud.means, cloud.quats, cloud.scales, cloud.opacities, cloud.sh))
    return (cloud.means.astype(np.float64), cloud.quats, np.exp(cloud.log_scales.astype(np.float64)),
            1.0 / (1.0 + np.exp(-cloud.logit_opacities.astype(np.float64))), cloud.sh.astype(np.float64))


def _camera_points(means: np.ndarray, cam: Camera) -> np.ndarray:
    w2c = cam.world_to_cam
    return means @ w2c[:3, :3].T + w2c[:3, 3]


def project_means(means: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """Pixel coordinates (N, 2) of the means (pixel (i, j) has its centre at (i + 0.5, j + 0.5)) and their
    camera depths z (N,); points with z <= 0 are projected as if z were 1 (they are culled later)."""
    p = _camera_points(means, cam)
    z = p[:, 2]
    zs = np.where(z > 0, z, 1.0)
    return np.stack([cam.fx * p[:, 0] / zs + cam.cx, cam.fy * p[:, 1] / zs + cam.cy], 1), z


def covariance_2d(means: np.ndarray, quats: np.ndarray, scales: np.ndarray, cam: Camera) -> np.ndarray:
    """Image-plane covariances (N, 2, 2): EWA, J W R S S^T R^T W^T J^T with the projection's Jacobian J at
    the mean (x/z, y/z clamped to 0.3 tan(fov/2) beyond the image, as gsplat does), plus the low-pass."""
    w2c = cam.world_to_cam
    p = _camera_points(means, cam)
    z = p[:, 2]
    m = quat_to_matrix(quats) * scales[:, None, :]
    cov_c = w2c[:3, :3] @ (m @ m.transpose(0, 2, 1)) @ w2c[:3, :3].T
    tan_x, tan_y = 0.5 * cam.width / cam.fx, 0.5 * cam.height / cam.fy
    zs = np.where(z > 0, z, 1.0)
    lim_x = (cam.cx / cam.fx + 0.3 * tan_x, (cam.width - cam.cx) / cam.fx + 0.3 * tan_x)
    lim_y = (cam.cy / cam.fy + 0.3 * tan_y, (cam.height - cam.cy) / cam.fy + 0.3 * tan_y)
    tx = np.clip(p[:, 0] / zs, -lim_x[0], lim_x[1]) * zs
    ty = np.clip(p[:, 1] / zs, -lim_y[0], lim_y[1]) * zs
    jac = np.zeros((len(z), 2, 3))
    jac[:, 0, 0] = cam.fx / zs
    jac[:, 0, 2] = -cam.fx * tx / zs**2
    jac[:, 1, 1] = cam.fy / zs
    jac[:, 1, 2] = -cam.fy * ty / zs**2
    return jac @ cov_c @ jac.transpose(0, 2, 1) + LOW_PASS * np.eye(2)


def colours(means: np.ndarray, sh: np.ndarray, cam: Camera) -> np.ndarray:
    """View-dependent colours (N, 3): max(0, 0.5 + sum_k c_k Y_k(d)), d the unit direction camera -> mean."""
    dirs = means - cam.position
    dirs = dirs / np.linalg.norm(dirs, axis=1, keepdims=True)
    return eval_sh_colour(sh, dirs)


def composite(uv: np.ndarray, cov2: np.ndarray, opacity: np.ndarray, colour: np.ndarray, z: np.ndarray,
              width: int, height: int, background=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, ...]:
    """Front-to-back alpha blending at every pixel centre of a width x height image, in depth order (ties
    in input order); Gaussians with z < NEAR or opacity < 1/255 are dropped. Per pixel and Gaussian:
    alpha = min(0.99, o exp(-d^T cov2^-1 d / 2)); skipped when alpha < 1/255; the pixel stops before a
    Gaussian that would bring its transmittance T below 1e-4. Returns rgb (H, W, 3) clipped to [0, 1] with
    the background behind T, depth (H, W) (expected z, alpha-normalised; 0 where alpha is 0) and alpha
    (H, W) = 1 - T."""
    inv = np.linalg.inv(cov2)
    keep = np.flatnonzero((z >= NEAR) & (opacity >= ALPHA_MIN))
    keep = keep[np.argsort(z[keep], kind="stable")]
    jj, ii = np.mgrid[0:height, 0:width]
    pix = np.stack([ii.ravel() + 0.5, jj.ravel() + 0.5], 1)
    T = np.ones(len(pix))
    done = np.zeros(len(pix), bool)
    rgb = np.zeros((len(pix), 3))
    dep = np.zeros(len(pix))
    for g in keep:
        d = pix - uv[g]
        d2 = np.einsum("pi,ij,pj->p", d, inv[g], d)
        alpha = np.minimum(ALPHA_MAX, opacity[g] * np.exp(-0.5 * d2))
        ok = (~done) & (alpha >= ALPHA_MIN)
        test_t = T * (1 - alpha)
        stop = ok & (test_t < T_MIN)
        done |= stop
        ok &= ~stop
        wgt = np.where(ok, alpha * T, 0.0)
        rgb += wgt[:, None] * colour[g]
        dep += wgt * z[g]
        T = np.where(ok, test_t, T)
    alpha_img = 1 - T
    rgb = np.clip(rgb + T[:, None] * np.asarray(background), 0, 1)
    dep = np.where(alpha_img > 0, dep / np.where(alpha_img > 0, alpha_img, 1), 0)
    shape = (height, width)
    return rgb.reshape(*shape, 3), dep.reshape(shape), alpha_img.reshape(shape)


def reference_render(cloud: GaussianCloud | DeviceGaussians, cam: Camera,
                     background=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view in float64: (rgb (H, W, 3), depth (H, W), alpha (H, W)), the stages above in turn."""
    means, quats, scales, opacity, sh = _host(cloud)
    uv, z = project_means(means, cam)
    cov2 = covariance_2d(means, quats, scales, cam)
    return composite(uv, cov2, opacity, colours(means, sh, cam), z, cam.width, cam.height, background)


def render_views(views: list[tuple[GaussianCloud | DeviceGaussians, Camera]], background: np.ndarray,
                 device: str, threads: int) -> list[RenderOutput]:
    """The "reference" backend (see render.render_batch): each view on the host, images as float32."""
    outs = []
    for cloud, cam in views:
        rgb, depth, alpha = reference_render(cloud, cam, background)
        outs.append(RenderOutput(rgb.astype(np.float32), depth.astype(np.float32), alpha.astype(np.float32)))
    return outs
