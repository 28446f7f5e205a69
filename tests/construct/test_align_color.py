"""align-color: a hidden degree-2 colour map is recovered from image pairs with noise and 10 % outlier
pixels (mean error < 1/255 on inliers); IRLS beats plain least squares when outliers are present."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.construct.align_color import before_after_grid, fit_color_map, fit_pairs, load_pairs
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.colormap import apply_color_map, identity_color_map, map_colors


def _hidden_map(rng) -> np.ndarray:
    a = identity_color_map(2)
    a[:, 0] = rng.uniform(-0.05, 0.05, 3)  # offsets
    a[:, 1:4] = np.diag(rng.uniform(0.8, 1.1, 3)) + rng.uniform(-0.05, 0.05, (3, 3))  # gains + cross-talk
    a[:, 4:] = rng.uniform(-0.08, 0.08, (3, 6))  # quadratic and cross terms
    return a


def _pixels(rng, n, outliers=0.1, noise=0.01):
    a = _hidden_map(rng)
    src = rng.uniform(0.05, 0.95, (n, 3))
    dst = map_colors(src, a) + rng.normal(0, noise, (n, 3))
    bad = rng.random(n) < outliers
    dst[bad] = rng.uniform(0, 1, (bad.sum(), 3))
    return a, src, dst, bad


def test_irls_recovers_the_hidden_map_and_beats_least_squares():
    rng = np.random.default_rng(0)
    a, src, dst, bad = _pixels(rng, 40000)
    irls = fit_color_map(src, dst, degree=2)
    plain = fit_color_map(src, dst, degree=2, robust=False)
    truth = map_colors(src[~bad], a)
    err_irls = np.abs(map_colors(src[~bad], irls.coeffs) - truth).mean()
    err_ls = np.abs(map_colors(src[~bad], plain.coeffs) - truth).mean()
    assert err_irls < 1 / 255
    assert err_ls > 3 * err_irls and err_ls > 1 / 255
    # the outliers end with (near) zero weight, the inliers keep theirs
    assert np.median(irls.weights[bad]) < 0.05 * np.median(irls.weights[~bad])
    assert 0 < irls.iterations <= 50


def test_degree_one_map_is_exact_without_noise():
    rng = np.random.default_rng(1)
    a = np.concatenate([rng.uniform(-0.1, 0.1, (3, 1)), np.eye(3) * 0.9 + 0.02], axis=1)
    src = rng.uniform(0, 1, (500, 3))
    fit = fit_color_map(src, map_colors(src, a, 1), degree=1)
    np.testing.assert_allclose(fit.coeffs, a, atol=1e-9)


def test_image_pairs_with_masks_recover_the_map(tmp_path):
    import imageio.v3 as iio

    rng = np.random.default_rng(2)
    a = _hidden_map(rng)
    h, w = 96, 128
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    truth_err = []
    for k in range(3):
        phase = rng.uniform(0, 6, 3)
        waves = [3 * xx + phase[0], 4 * yy + phase[1], 2 * (xx + yy) + phase[2]]
        src = 0.5 + 0.42 * np.sin(np.stack(waves, -1))
        src8 = (src * 255 + 0.5).astype(np.uint8)
        real = map_colors(src8 / 255.0, a) + rng.normal(0, 0.01, src.shape)
        bad = rng.random((h, w)) < 0.07  # salt noise
        bad[10:30, 20:60] = True  # and an occluder the render does not have
        real[bad] = rng.uniform(0, 1, (bad.sum(), 3))
        iio.imwrite(tmp_path / f"cam{k}_render.png", src8)
        iio.imwrite(tmp_path / f"cam{k}_real.png", (np.clip(real, 0, 1) * 255 + 0.5).astype(np.uint8))
        mask = np.ones((h, w), np.uint8) * 255
        mask[:, -8:] = 0  # a part of the image that belongs to another part of the scene
        iio.imwrite(tmp_path / f"cam{k}_mask.png", mask)
        truth_err.append((src8, bad))
    pairs = load_pairs(tmp_path)
    assert [p[0] for p in pairs] == ["cam0", "cam1", "cam2"]
    fit = fit_pairs(pairs, degree=2)
    for src8, bad in truth_err:
        s = src8[~bad] / 255.0
        assert np.abs(map_colors(s, fit.coeffs) - map_colors(s, a)).mean() < 1 / 255
    grid = before_after_grid(pairs, fit.coeffs, 2)
    assert grid.shape == (3 * h, 3 * w, 3) and grid.dtype == np.uint8


def test_fitted_map_applies_to_gaussian_base_colours():
    rng = np.random.default_rng(3)
    a, src, dst, _ = _pixels(rng, 5000, outliers=0.0, noise=0.0)
    fit = fit_color_map(src, dst)
    cloud = GaussianCloud(np.zeros((4, 3)), np.tile([1.0, 0, 0, 0], (4, 1)), np.zeros((4, 3)), np.zeros(4),
                          ((src[:4] - 0.5) / 0.28209479177387814)[:, None, :])
    mapped = apply_color_map(cloud, fit.coeffs, 2)
    np.testing.assert_allclose(mapped.base_colours, dst[:4], atol=1e-5)


def test_bad_inputs_are_named(tmp_path):
    with pytest.raises(ValueError, match="same number of pixels"):
        fit_color_map(np.zeros((10, 3)), np.zeros((11, 3)))
    with pytest.raises(ValueError, match="usable pixels"):
        fit_color_map(np.zeros((10, 3)), np.zeros((10, 3)))
    with pytest.raises(FileNotFoundError, match="no NAME_render.png"):
        load_pairs(tmp_path)
    (tmp_path / "a_render.png").write_bytes(b"x")
    with pytest.raises(FileNotFoundError, match="a_real.png"):
        load_pairs(tmp_path)
