"""The reference renderer (twinbench.gaussians.reference), stage by stage as gsplat's tests check theirs:
projection of the means, 2D covariance, SH colour, compositing, each against an independent computation;
then the backend registry. (The Warp backend against this reference: test_gaussian_render.py.)"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from twinbench.errors import InputError
from twinbench.gaussians import reference as R
from twinbench.gaussians.camera import Camera
from twinbench.gaussians.render import backends, register_backend, render, render_batch
from twinbench.gaussians.render_rules import RenderOutput

C0, C1 = 0.28209479177387814, 0.4886025119029199


def _cam() -> Camera:
    return Camera.look_at((1.0, 0.25, 0.35), (0.0, 0.0, 0.0), fx=60.0, fy=55.0, width=72, height=56)


def test_means_project_by_the_pinhole_model_with_pixel_centres_at_half_integers():
    cam = _cam()
    rng = np.random.default_rng(0)
    means = rng.uniform(-0.2, 0.2, (50, 3))
    uv, z = R.project_means(means, cam)
    hom = np.c_[means, np.ones(50)] @ np.linalg.inv(cam.cam_to_world).T  # independent: invert the pose
    np.testing.assert_allclose(z, hom[:, 2], rtol=1e-12)
    pix = hom[:, :3] @ cam.K.T
    np.testing.assert_allclose(uv, pix[:, :2] / pix[:, 2:], rtol=1e-12, atol=1e-9)
    # a small Gaussian drawn where it projects: the brightest pixel is the one whose centre is nearest
    on_axis = Camera(fx=80.0, fy=80.0, cx=20.0, cy=15.0, width=40, height=30)
    point = np.array([[0.031, -0.017, 1.0]])  # u = 80 * 0.031 + 20 = 22.48, v = 80 * -0.017 + 15 = 13.64
    uv1, _ = R.project_means(point, on_axis)
    np.testing.assert_allclose(uv1[0], [22.48, 13.64])
    rgb, _, alpha = R.composite(uv1, np.eye(2)[None] * 0.5, np.array([0.9]), np.ones((1, 3)), np.array([1.0]),
                                on_axis.width, on_axis.height)
    row, col = np.unravel_index(np.argmax(alpha), alpha.shape)
    assert (col, row) == (22, 13)  # centre (22.5, 13.5)


def test_2d_covariance_is_the_ewa_projection_plus_the_low_pass():
    cam = _cam()
    rng = np.random.default_rng(1)
    n = 20
    means = rng.uniform(-0.1, 0.1, (n, 3))
    quats = rng.normal(size=(n, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    scales = np.exp(rng.uniform(-5, -2.5, (n, 3)))
    got = R.covariance_2d(means, quats, scales, cam)
    # independent: scipy rotations (xyzw), the Jacobian of the pixel projection by central differences
    rot = Rotation.from_quat(quats[:, [1, 2, 3, 0]]).as_matrix()
    sigma = rot @ (scales[:, :, None] ** 2 * np.eye(3)) @ rot.transpose(0, 2, 1)
    def uv(point):
        return R.project_means(point[None], cam)[0][0]

    for i in range(n):
        h = 1e-6  # d(uv)/d(world point), 2 x 3
        jac = np.stack([(uv(means[i] + h * e) - uv(means[i] - h * e)) / (2 * h) for e in np.eye(3)], axis=1)
        want = jac @ sigma[i] @ jac.T + 0.3 * np.eye(2)
        np.testing.assert_allclose(got[i], want, rtol=1e-5, atol=1e-9)


def test_sh_colours_match_the_analytic_degree_0_and_1_values():
    cam = _cam()
    means = np.array([[0.0, 0.0, 0.0], [0.1, -0.2, 0.05]])
    sh = np.zeros((2, 4, 3))
    sh[:, 0] = [[0.4, -0.2, 1.0], [-3.0, 0.1, 0.0]]  # the second's red clamps at 0
    sh[:, 1:] = np.random.default_rng(2).normal(0, 0.3, (2, 3, 3))
    d = means - cam.position
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    x, y, z = d[:, :1], d[:, 1:2], d[:, 2:]
    deg0 = np.maximum(0.5 + C0 * sh[:, 0], 0)
    np.testing.assert_allclose(R.colours(means, sh[:, :1], cam), deg0, rtol=1e-12)
    deg1 = np.maximum(0.5 + C0 * sh[:, 0] - C1 * y * sh[:, 1] + C1 * z * sh[:, 2] - C1 * x * sh[:, 3], 0)
    np.testing.assert_allclose(R.colours(means, sh, cam), deg1, rtol=1e-12)
    assert deg0[1, 0] == 0.0


def _blend(layers, background=(0.0, 0.0, 0.0)):
    """One pixel by hand: layers (alpha before the clamp, colour, depth) front to back."""
    t, rgb, dep = 1.0, np.zeros(3), 0.0
    for a, colour, z in layers:
        a = min(a, 0.99)
        if a < 1 / 255:
            continue
        if t * (1 - a) < 1e-4:
            break
        rgb, dep, t = rgb + a * t * np.asarray(colour), dep + a * t * z, t * (1 - a)
    return np.clip(rgb + t * np.asarray(background), 0, 1), dep / (1 - t) if t < 1 else 0.0, 1 - t


def test_two_overlapping_gaussians_blend_front_to_back():
    # a 3 x 1 image; a wide red Gaussian behind (z = 2) and a narrow green one in front (z = 1) at x = 1.5
    uv = np.array([[1.5, 0.5], [1.5, 0.5]])
    cov = np.array([np.eye(2) * 4.0, np.eye(2) * 0.5])
    op = np.array([0.8, 0.6])
    col = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    z = np.array([2.0, 1.0])
    bg = (0.1, 0.2, 0.3)
    rgb, dep, alpha = R.composite(uv, cov, op, col, z, 3, 1, bg)
    for px in range(3):
        dx = px + 0.5 - 1.5
        green, red = 0.6 * np.exp(-0.5 * dx * dx / 0.5), 0.8 * np.exp(-0.5 * dx * dx / 4.0)
        want = _blend([(green, col[1], 1.0), (red, col[0], 2.0)], bg)
        np.testing.assert_allclose(rgb[0, px], want[0], rtol=1e-12)
        assert dep[0, px] == pytest.approx(want[1], rel=1e-12) and alpha[0, px] == pytest.approx(want[2])
    # at the centre the green one is drawn first: depth between 1 and 2, nearer 1
    assert dep[0, 1] == pytest.approx(1.25, abs=0.25)


def test_compositing_clamps_alpha_skips_faint_gaussians_and_stops_at_low_transmittance():
    one = np.array([[0.5, 0.5]])
    cov = np.eye(2)[None] * 0.01  # the pixel centre sits on the mean: alpha = opacity
    # clamp: opacity 1.0 draws with alpha 0.99
    rgb, _, alpha = R.composite(one, cov, np.array([1.0]), np.ones((1, 3)), np.array([1.0]), 1, 1)
    assert alpha[0, 0] == pytest.approx(0.99) and rgb[0, 0, 0] == pytest.approx(0.99)
    # skip: a Gaussian whose alpha at the pixel is below 1/255 adds nothing, one just above it does
    uv2, cov2 = np.repeat(one, 2, 0), np.repeat(cov, 2, 0)
    two_col, z2 = np.array([[1.0, 0, 0], [0, 1.0, 0]]), np.array([1.0, 2.0])
    _, _, a_lo = R.composite(uv2, cov2, np.array([0.5, 0.99 / 255]), two_col, z2, 1, 1)
    assert a_lo[0, 0] == pytest.approx(0.5, abs=1e-15)
    rgb_hi, _, a_hi = R.composite(uv2, cov2, np.array([0.5, 1.01 / 255]), two_col, z2, 1, 1)
    assert a_hi[0, 0] == pytest.approx(1 - 0.5 * (1 - 1.01 / 255)) and rgb_hi[0, 0, 1] > 0
    # stop: behind two opaque layers (T = 1e-4 after them) a third would bring T below 1e-4: not drawn
    uv3, cov3 = np.repeat(one, 3, 0), np.repeat(cov, 3, 0)
    cols3 = np.array([[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]])
    rgb3, dep3, a3 = R.composite(uv3, cov3, np.array([1.0, 1.0, 0.5]), cols3, np.array([1.0, 2.0, 3.0]), 1, 1)
    want = _blend([(1.0, cols3[0], 1.0), (1.0, cols3[1], 2.0), (0.5, cols3[2], 3.0)])
    assert rgb3[0, 0, 2] == 0.0 and want[0][2] == 0.0
    np.testing.assert_allclose(rgb3[0, 0], want[0], rtol=1e-12)
    assert a3[0, 0] == pytest.approx(want[2]) and dep3[0, 0] == pytest.approx(want[1])
    # depth order, not input order: the same three listed back to front give the same pixel
    rev = R.composite(uv3, cov3, np.array([0.5, 1.0, 1.0]), cols3[::-1], np.array([3.0, 2.0, 1.0]), 1, 1)
    np.testing.assert_array_equal(rev[0], rgb3)
    # culled: behind the near plane, or opacity below 1/255
    _, _, a_cull = R.composite(uv2, cov2, np.array([0.9, 0.9]), two_col, np.array([0.005, -1.0]), 1, 1)
    assert a_cull[0, 0] == 0.0


def test_backends_are_a_registry(make_cloud):
    assert {"warp", "gsplat", "reference"} <= set(backends())
    cloud, cam = make_cloud(40, degree=1, seed=3), Camera.look_at((1.0, 0.2, 0.3), (0, 0, 0), fx=30.0,
                                                                   width=24, height=20)
    ref = render(cloud, cam, backend="reference")
    assert isinstance(ref, RenderOutput) and ref.rgb.dtype == np.float32
    np.testing.assert_array_equal(ref.rgb, R.reference_render(cloud, cam)[0].astype(np.float32))
    warp = render(cloud, cam, backend="warp")
    assert np.abs(warp.rgb - ref.rgb).max() < 2e-3 and ref.alpha.max() > 0.1
    # the reference backend also takes Warp arrays
    on_device = render(cloud.to_device("cpu"), cam, backend="reference")
    np.testing.assert_allclose(on_device.rgb, ref.rgb, atol=1e-6)
    with pytest.raises(InputError, match=r"unknown backend 'opengl'.*'warp'.*'gsplat'.*'reference'"):
        render(cloud, cam, backend="opengl")
    seen = []

    def flat(views, background, device, threads):
        seen.append((len(views), device, threads))
        return [RenderOutput(np.zeros((c.height, c.width, 3), np.float32), np.zeros((c.height, c.width),
                             np.float32), np.zeros((c.height, c.width), np.float32)) for _, c in views]

    register_backend("flat-test", flat)
    try:
        outs = render_batch([(cloud, cam), (cloud, cam)], backend="flat-test", threads=3)
        assert len(outs) == 2 and seen == [(2, "cpu", 3)] and "flat-test" in backends()
    finally:
        from twinbench.gaussians import render as render_module

        render_module._BACKENDS.pop("flat-test")
    with pytest.raises(InputError):
        register_backend("auto", flat)
