"""Warp tile renderer vs a brute-force NumPy reference, plus analytic single-Gaussian checks."""

from __future__ import annotations

import multiprocessing
import os

import numpy as np
import pytest
import warp as wp

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import SH_C0, GaussianCloud
from twinbench.gaussians.render import RenderOutput, gsplat_available, render
from twinbench.gaussians.warp_raster import _claim


def _cam(width=72, height=56, eye=(1.0, 0.25, 0.35), target=(0.0, 0.0, 0.0), fx=60.0, **kw) -> Camera:
    return Camera.look_at(eye, target, fx=fx, width=width, height=height, **kw)


def _assert_matches(out: RenderOutput, ref, tol=2e-3):
    rgb, depth, alpha = ref
    assert out.rgb.shape == rgb.shape and out.rgb.dtype == np.float32
    assert np.abs(out.rgb - rgb).max() < tol
    assert np.abs(out.alpha - alpha).max() < tol
    # depth is alpha-normalised; compare where the pixel is covered enough to be well conditioned
    covered = alpha > 0.05
    assert np.abs(out.depth - depth)[covered].max() < 1e-3 * depth[covered].max() + 1e-4


@pytest.mark.parametrize(
    "degree, anisotropic, seed",
    [(0, False, 0), (3, False, 1), (0, True, 2), (3, True, 3), (1, True, 4), (2, False, 5)],
)
def test_warp_matches_bruteforce_reference(make_cloud, ref_render, degree, anisotropic, seed):
    cloud = make_cloud(120, degree=degree, anisotropic=anisotropic, seed=seed, spread=0.35)
    cam = _cam()
    bg = (0.1, 0.2, 0.3)
    out = render(cloud, cam, background=bg)
    ref = ref_render(cloud, cam, bg)
    assert ref[2].max() > 0.9, "scene should cover some pixels fully"
    _assert_matches(out, ref)


def test_many_tiles_and_tile_boundaries(make_cloud, ref_render):
    # 10 x 8 tiles with a ragged last column/row; Gaussians of 1-20 px straddle many tile borders
    cloud = make_cloud(600, degree=2, anisotropic=True, seed=21, spread=0.4, log_scale=(-4.5, -2.3))
    cam = _cam(width=157, height=121, fx=120.0)
    out = render(cloud, cam, background=(1.0, 1.0, 1.0), threads=2)
    _assert_matches(out, ref_render(cloud, cam, (1.0, 1.0, 1.0)))


def test_stages_split_over_threads_equal_one_thread(make_cloud, monkeypatch):
    """Projection and pair emission split over the threads only from _SPLIT_PROJECT Gaussians and
    _SPLIT_PAIRS pairs (a hand-off costs more below); split from one, a render equals one thread's."""
    from twinbench.gaussians import warp_raster

    cloud = make_cloud(600, degree=2, anisotropic=True, seed=22, spread=0.4, log_scale=(-4.5, -2.3))
    cam = _cam(width=157, height=121, fx=120.0)
    one = render(cloud, cam, threads=1)
    monkeypatch.setattr(warp_raster, "_SPLIT_PROJECT", 1)
    monkeypatch.setattr(warp_raster, "_SPLIT_PAIRS", 1)
    split = render(cloud, cam, threads=2)
    for a, b in ((one.rgb, split.rgb), (one.depth, split.depth), (one.alpha, split.alpha)):
        np.testing.assert_array_equal(b, a)


@wp.kernel
def _take_slots(counter: wp.array(dtype=wp.int32), owner: int, taken: wp.array(dtype=wp.int32)):
    slot = _claim(counter)
    if slot < taken.shape[0]:
        taken[slot] = taken[slot] + owner


def test_tile_claims_are_atomic_across_threads():
    """The CPU tile kernel's threads share a view by claiming tiles from one counter (`_claim`, a native
    atomic add: Warp's own atomic_add is a plain add on CPU). Two threads claiming 2,000,000 slots at once
    take every slot exactly once and count every claim (four rounds)."""
    from twinbench.gaussians.threads import run_threads

    n = 2_000_000
    for _ in range(4):  # a race shows within a round or two; four keep a broken claim from slipping by
        counter = wp.zeros(1, dtype=wp.int32, device="cpu")
        taken = wp.zeros(n, dtype=wp.int32, device="cpu")
        wp.launch(_take_slots, dim=0, inputs=[counter, 1], outputs=[taken], device="cpu")  # compile first
        args = [([counter, owner], [taken]) for owner in (1, 2)]
        run_threads([lambda a=a: wp.launch(_take_slots, dim=n, inputs=a[0], outputs=a[1], device="cpu")
                     for a in args])
        assert int(counter.numpy()[0]) == 2 * n
        assert np.isin(taken.numpy(), (1, 2)).all()  # each slot taken once (two takers: 3; none: 0)


def test_radix_sort_path_matches_bruteforce_reference_on_cpu(make_cloud, ref_render):
    """The CUDA pipeline's pair sort (Warp radix sorts, scan, tile-range kernel) run on CPU."""
    from twinbench.gaussians.warp_raster import _render_warp_one

    cloud = make_cloud(600, degree=2, anisotropic=True, seed=21, spread=0.4, log_scale=(-4.5, -2.3))
    cam = _cam(width=157, height=121, fx=120.0)
    bg = np.array([1.0, 1.0, 1.0], np.float32)
    out = _render_warp_one(cloud.to_device("cpu"), cam, bg, 1, host_sort=False)
    _assert_matches(out, ref_render(cloud, cam, bg))
    np.testing.assert_array_equal(out.rgb, _render_warp_one(cloud.to_device("cpu"), cam, bg, 1).rgb)


def test_behind_camera_offscreen_and_offcentre_principal_point(make_cloud, ref_render):
    # camera inside the cloud: many Gaussians behind it or beside the image; principal point off centre
    cloud = make_cloud(200, degree=3, anisotropic=True, seed=7, spread=0.5, log_scale=(-3.5, -2.0))
    cam = Camera.look_at(
        (0.05, 0.0, 0.02), (1.0, 0.1, 0.0), fx=40.0, fy=45.0, width=64, height=48, cx=20.0, cy=30.0
    )
    w2c = cam.world_to_cam
    z = cloud.means @ w2c[:3, 2] + w2c[2, 3]
    assert (z < 0).sum() > 50, "the scene must put Gaussians behind the camera"
    out = render(cloud, cam)
    _assert_matches(out, ref_render(cloud, cam))


def test_dense_opaque_scene_hits_early_termination(make_cloud, ref_render):
    cloud = make_cloud(400, seed=11, spread=0.15, log_scale=(-2.5, -1.8))
    cloud.logit_opacities[:] = 6.0
    cam = _cam(width=48, height=40)
    ref = ref_render(cloud, cam)
    assert (ref[2] > 1 - 1.1e-4).mean() > 0.2, "many pixels should saturate (transmittance < 1e-4 stop)"
    _assert_matches(render(cloud, cam), ref)


def test_camera_list_and_threads_agree(make_cloud):
    cloud = make_cloud(150, degree=1, seed=3)
    cams = [_cam(), _cam(width=40, height=33, eye=(-0.8, 0.6, 0.5))]
    outs = render(cloud, cams, threads=2)
    assert isinstance(outs, list) and len(outs) == 2
    assert outs[1].rgb.shape == (33, 40, 3)
    single = render(cloud, cams[1], threads=1)
    np.testing.assert_array_equal(outs[1].rgb, single.rgb)
    dev = cloud.to_device("cpu")
    np.testing.assert_array_equal(render(dev, cams[0]).rgb, outs[0].rgb)


def _single(z=2.0, sigma=0.02, opacity=0.8, colour=(0.9, 0.4, 0.1)):
    dc = (np.asarray(colour) - 0.5) / SH_C0
    return GaussianCloud(
        means=[[0.0, 0.0, z]],
        quats=[[1.0, 0, 0, 0]],
        log_scales=np.log([[sigma, sigma, sigma]]),
        logit_opacities=[np.log(opacity / (1 - opacity))],
        sh=dc.reshape(1, 1, 3),
    )


def test_single_isotropic_gaussian_peak_and_width():
    f, z, sigma, opacity, colour = 100.0, 2.0, 0.03, 0.8, np.array([0.9, 0.4, 0.1])
    # camera at the origin looking along +z; principal point at the centre of pixel (40, 30)
    cam = Camera(fx=f, fy=f, cx=40.5, cy=30.5, width=81, height=61)
    out = render(_single(z, sigma, opacity, colour), cam)
    np.testing.assert_allclose(out.rgb[30, 40], opacity * colour, atol=1e-5)
    assert out.alpha[30, 40] == pytest.approx(opacity, abs=1e-6)
    assert out.depth[30, 40] == pytest.approx(z, rel=1e-5)
    # footprint: alpha(dx) = o exp(-dx^2 / (2 s^2)) with s^2 = (sigma f / z)^2 + 0.3 (low-pass)
    s_expected = np.sqrt((sigma * f / z) ** 2 + 0.3)
    dx = np.arange(1, 5)
    s_row = np.sqrt(dx**2 / (2 * np.log(opacity / out.alpha[30, 40 + dx])))
    s_col = np.sqrt(dx**2 / (2 * np.log(opacity / out.alpha[30 + dx, 40])))
    np.testing.assert_allclose(s_row, s_expected, rtol=1e-3)
    np.testing.assert_allclose(s_col, s_expected, rtol=1e-3)
    # nothing is drawn where alpha would fall below 1/255
    assert out.alpha[30, 40 + 8] == 0.0 and out.alpha[30, 40 + 5] > 0


@pytest.mark.parametrize("seed", range(4))
def test_single_extreme_ellipses_match_reference_per_pixel(ref_render, seed):
    """The rasteriser evaluates o exp(-d^2/2) at every pixel of a footprint row at once (a vectorised
    polynomial exp): on one Gaussian at a time (needles across the image, 45-degree slivers, sub-pixel dots
    at the low-pass limit, discs wider than a tile) every pixel stays within 1e-4 of the float64 reference
    (float32 projection alone differs by ~3e-5), but for pixels at the alpha >= 1/255 cut, where either side
    may round the other way."""
    rng = np.random.default_rng(seed)
    cam = _cam(width=96, height=80, fx=90.0)
    for k in range(12):
        quat = rng.normal(size=4)
        log_scales = np.log([rng.choice([1e-4, 3e-3, 0.2]), rng.choice([1e-4, 0.02, 0.3]), 1e-4])
        cloud = GaussianCloud(means=rng.uniform(-0.1, 0.1, size=(1, 3)), quats=[quat / np.linalg.norm(quat)],
                              log_scales=log_scales[None], logit_opacities=[rng.uniform(-3.0, 6.0)],
                              sh=rng.normal(scale=0.4, size=(1, 1, 3)))  # fmt: skip
        out = render(cloud, cam, background=(0.0, 0.0, 0.0), threads=1)
        rgb, _, alpha = ref_render(cloud, cam, (0.0, 0.0, 0.0))
        cut = np.abs(out.alpha - 1 / 255) < 1e-4
        cut |= np.abs(alpha - 1 / 255) < 1e-4
        assert (alpha > 0).sum() > 0, k
        assert np.abs(out.alpha - alpha)[~cut].max() < 1e-4, k
        assert np.abs(out.rgb - rgb)[~cut].max() < 1e-4, k
        assert cut.sum() <= 0.01 * cut.size, k


def test_row_exponent_floor_changes_no_pixel_and_keeps_alphas_normal():
    """The row step floors o exp(-d^2/2)'s exponent (`_EXP_FLOOR`): below the floor alpha < ALPHA_MIN for any
    opacity <= 1 (so no pixel changes), and at it every kept Gaussian's (opacity >= ALPHA_MIN) alpha times a
    live transmittance (>= T_MIN) is still a normal float32, never a subnormal (which Intel cores compute
    in microcode, ~2x slower tiles)."""
    from twinbench.gaussians.render_rules import ALPHA_MIN, T_MIN
    from twinbench.gaussians.warp_raster import _EXP_FLOOR, _ROW_SNIPPET

    low = np.exp(np.float32(_EXP_FLOOR))
    assert np.float32(1.0) * low < np.float32(ALPHA_MIN)
    assert np.float32(ALPHA_MIN) * low * np.float32(T_MIN) >= np.finfo(np.float32).tiny
    assert f"e > {_EXP_FLOOR!r}f ? e : {_EXP_FLOOR!r}f" in _ROW_SNIPPET


def test_raster_module_builds_for_cuda(tmp_path):
    """The CPU tile kernel's row steps are native C++ (`_composite_rows`), and Warp builds a module's kernels
    for every device it runs on: the module must also compile for CUDA. Checked with Warp's NVRTC, which
    needs no GPU, so that a machine without one catches a snippet CUDA would refuse."""
    import warp as wp
    from warp._src import context  # NVRTC's architectures have no public accessor

    from twinbench.gaussians import warp_raster

    wp.init()
    archs = sorted(getattr(context.runtime, "nvrtc_supported_archs", ()))
    if not archs:
        pytest.skip("this Warp build has no NVRTC")
    paths = wp.compile_aot_module(warp_raster, arch=80 if 80 in archs else archs[-1], module_dir=tmp_path)
    assert paths and all(p.stat().st_size > 0 for p in paths)


def _render_in_child(queue, cloud, cam) -> None:
    queue.put(render(cloud, cam, threads=2).rgb)


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs os.fork")
def test_threaded_render_in_a_forked_child(make_cloud):
    """The render threads' pool, started in this process, is not inherited by a forked child (gymnasium's
    AsyncVectorEnv forks on Linux): the child starts its own instead of waiting on threads that do not
    exist there."""
    cloud = make_cloud(300, degree=1, seed=7)
    cam = _cam()
    want = render(cloud, cam, threads=2).rgb  # the pool now runs in this process
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    child = ctx.Process(target=_render_in_child, args=(queue, cloud, cam))
    child.start()
    try:
        got = queue.get(timeout=120)
    finally:
        child.join(timeout=30)
        if child.is_alive():
            child.kill()
    np.testing.assert_array_equal(got, want)


def test_near_plane_cull_and_empty_background():
    cam = Camera(fx=50.0, fy=50.0, cx=16.0, cy=16.0, width=32, height=32)
    behind = _single(z=-1.0)
    too_near = _single(z=0.005)
    for cloud in (behind, too_near, GaussianCloud.concatenate([behind, too_near]).subset([])):
        out = render(cloud, cam, background=(0.2, 0.4, 0.6))
        np.testing.assert_allclose(out.rgb, np.broadcast_to([0.2, 0.4, 0.6], out.rgb.shape), atol=1e-7)
        assert out.alpha.max() == 0.0 and out.depth.max() == 0.0
    assert render(_single(z=0.5), cam).alpha.max() > 0.5


def test_rgb_uint8_and_bad_arguments(make_cloud):
    out = render(make_cloud(20), _cam(width=16, height=16))
    img = out.rgb_uint8()
    assert img.dtype == np.uint8 and img.shape == (16, 16, 3)
    np.testing.assert_array_equal(img, np.rint(out.rgb * 255).astype(np.uint8))
    with pytest.raises(ValueError, match="backend"):
        render(make_cloud(5), _cam(), backend="opengl")
    with pytest.raises(ValueError, match="background"):
        render(make_cloud(5), _cam(), background=(1, 2))
    with pytest.raises(ValueError, match="empty"):
        render(make_cloud(5), [])


@pytest.mark.skipif(gsplat_available(), reason="gsplat is installed; this checks the missing-extra error")
def test_gsplat_backend_missing_names_the_extra(make_cloud):
    with pytest.raises(ImportError, match=r"twinbench\[gsplat\]"):
        render(make_cloud(5), _cam(), backend="gsplat", device="cuda:0")


@pytest.mark.gpu
def test_warp_cuda_matches_cpu(make_cloud):
    cloud = make_cloud(300, degree=3, anisotropic=True, seed=5)
    cam = _cam(width=100, height=70)
    cpu = render(cloud, cam, backend="warp", device="cpu")
    gpu = render(cloud, cam, backend="warp", device="cuda:0")
    assert np.abs(cpu.rgb - gpu.rgb).max() < 1e-4
    assert np.abs(cpu.alpha - gpu.alpha).max() < 1e-4


@pytest.mark.gpu
def test_gsplat_close_to_warp(make_cloud):
    pytest.importorskip("gsplat", reason="needs the gsplat extra: pip install twinbench[gsplat]")
    cloud = make_cloud(300, degree=3, seed=6)
    cam = _cam(width=96, height=64)
    ref = render(cloud, cam, backend="warp", device="cuda:0")
    out = render(cloud, cam, backend="gsplat", device="cuda:0")
    # gsplat's footprint is a 3-sigma radius, ours the alpha >= 1/255 ellipse: tiny differences at edges
    assert np.abs(out.rgb - ref.rgb).mean() < 2e-3


def test_render_batch_of_several_clouds_and_cameras_equals_each_view_alone(make_cloud, ref_render):
    """Many worlds' views in one call: dealt over threads, each image the same as rendering it alone."""
    from twinbench.gaussians.render import render_batch

    clouds = [make_cloud(150, degree=1, anisotropic=True, seed=s, spread=0.3) for s in (7, 8, 9)]
    cams = [_cam(), _cam(width=40, height=64, eye=(0.2, -1.0, 0.5), fx=50.0)]
    views = [(c, cam) for c in clouds for cam in cams]  # a host cloud, uploaded once for its two views
    bg = (0.2, 0.1, 0.0)
    for threads in (1, 2, 3):
        outs = render_batch(views, background=bg, threads=threads)
        assert len(outs) == len(views)
        for (cloud, cam), out in zip(views, outs, strict=True):
            alone = render(cloud, cam, background=bg, threads=1)
            np.testing.assert_array_equal(out.rgb, alone.rgb)
            np.testing.assert_array_equal(out.depth, alone.depth)
    _assert_matches(outs[3], ref_render(clouds[1], cams[1], bg))  # and right, not only consistent
    with pytest.raises(ValueError, match="no views"):
        render_batch([])
    with pytest.raises(ValueError, match="Camera objects"):
        render_batch([(clouds[0], "front")])


def test_one_launch_per_stage_batch_path_equals_each_view_alone_on_cpu(make_cloud, ref_render, monkeypatch):
    """render_batch's CUDA path (every view's records, sorts and tiles in one launch per stage) run on
    CPU: each image equals its view rendered alone with the same radix sorts, bit for bit, and matches
    the brute-force reference; views share clouds, differ in size, and one sees nothing."""
    from twinbench.gaussians.warp_raster import _render_warp_batch, _render_warp_one

    clouds = [make_cloud(n, degree=2, anisotropic=True, seed=s, spread=0.35).to_device("cpu")
              for n, s in ((300, 11), (170, 12))]
    cams = [_cam(width=157, height=121, fx=120.0), _cam(width=40, height=64, eye=(0.2, -1.0, 0.5), fx=50.0),
            _cam(eye=(5.0, 0.0, 0.3), target=(9.0, 0.0, 0.3))]  # looking away: an empty image
    views = [(clouds[0], cams[0]), (clouds[1], cams[1]), (clouds[0], cams[1]), (clouds[1], cams[2])]
    bg = np.array([0.3, 0.2, 0.1], np.float32)
    outs = _render_warp_batch(views, bg)
    for (g, cam), out in zip(views, outs, strict=True):
        alone = _render_warp_one(g, cam, bg, 1, host_sort=False)
        np.testing.assert_array_equal(out.rgb, alone.rgb)
        np.testing.assert_array_equal(out.depth, alone.depth)
        np.testing.assert_array_equal(out.alpha, alone.alpha)
    host = [make_cloud(n, degree=2, anisotropic=True, seed=s, spread=0.35) for n, s in ((300, 11), (170, 12))]
    _assert_matches(outs[0], ref_render(host[0], cams[0], bg))
    _assert_matches(outs[2], ref_render(host[0], cams[1], bg))
    assert outs[3].alpha.max() == 0.0 and np.allclose(outs[3].rgb, bg)
    # segments of one cloud (a twin's worlds) are read in place, not concatenated: same images
    from twinbench.gaussians.cloud import DeviceGaussians

    both = DeviceGaussians.concatenate(clouds)
    parts = [both.segment(0, 300), both.segment(300, 170)]
    assert parts[1].base == (both, 300) and parts[1].segment(20, 50).base == (both, 320)

    def no_copy(items):
        raise AssertionError("segments of one cloud were concatenated")

    monkeypatch.setattr(DeviceGaussians, "concatenate", staticmethod(no_copy))
    jobs = [(parts[i], cam) for i, cam in ((0, cams[0]), (1, cams[1]), (0, cams[1]))]
    seg_outs = _render_warp_batch(jobs, bg)
    for got, ref in zip(seg_outs, outs[:3], strict=True):
        np.testing.assert_array_equal(got.rgb, ref.rgb)
        np.testing.assert_array_equal(got.depth, ref.depth)
    with pytest.raises(ValueError, match="outside"):
        both.segment(400, 71)
    # a segment whose arrays were replaced since is rendered from its own arrays
    import dataclasses

    moved = dataclasses.replace(parts[1], means=clouds[0].means[:170])
    assert parts[1].parent() == (both, 300) and moved.parent() == (moved, 0)


@pytest.mark.gpu
def test_render_batch_on_cuda_matches_cpu(make_cloud):
    """The one-launch-per-stage batch on CUDA against the same views on CPU."""
    from twinbench.gaussians.render import render_batch

    clouds = [make_cloud(300, degree=3, anisotropic=True, seed=s) for s in (5, 6)]
    cams = [_cam(width=100, height=70), _cam(width=40, height=64, eye=(0.2, -1.0, 0.5), fx=50.0)]
    views = [(c, cam) for c in clouds for cam in cams]
    cpu = render_batch(views, backend="warp", device="cpu")
    gpu = render_batch([(c.to_device("cuda:0"), cam) for c, cam in views], backend="warp", device="cuda:0")
    for a, b in zip(cpu, gpu, strict=True):
        assert np.abs(a.rgb - b.rgb).max() < 1e-4
        assert np.abs(a.alpha - b.alpha).max() < 1e-4


def test_kernel_views_hold_each_camera_and_slot():
    """The warp renderer's per-view structs, written word by word into the array's memory, read back field
    by field as each camera's pose, intrinsics, Jacobian clamp and the batch's first slots."""
    from twinbench.gaussians import warp_raster as wr

    rng = np.random.default_rng(4)
    specs = []
    for _ in range(5):
        cam = Camera.look_at(rng.normal(size=3) + 3.0, rng.normal(size=3), fx=float(rng.uniform(50, 500)),
                             fy=float(rng.uniform(50, 500)), cx=float(rng.uniform(0, 300)),
                             cy=float(rng.uniform(0, 200)), width=int(rng.integers(10, 900)),
                             height=int(rng.integers(10, 600)))  # fmt: skip
        specs.append((cam, rng.uniform(0, 1, 3), *rng.integers(0, 10**6, 4).tolist()))
    got = wr._views(specs, "cpu").numpy()
    for row, (cam, bg, src, item, tile, pixel) in zip(got, specs, strict=True):
        w2c = cam.world_to_cam.astype(np.float32)
        np.testing.assert_array_equal(row["rot_wc"], w2c[:3, :3])
        np.testing.assert_array_equal(row["t_wc"], w2c[:3, 3])
        np.testing.assert_array_equal(row["cam_pos"], cam.position.astype(np.float32))
        intrinsics = np.float32([cam.fx, cam.fy, cam.cx, cam.cy])
        assert (row["fx"], row["fy"], row["cx"], row["cy"]) == tuple(intrinsics)
        assert (row["width"], row["height"], row["tiles_x"]) == (cam.width, cam.height, -(-cam.width // 16))
        assert (row["src"], row["item"], row["tile"], row["pixel"]) == (src, item, tile, pixel)
        tan_x = 0.5 * cam.width / cam.fx
        np.testing.assert_allclose(row["lim"][:2], [cam.cx / cam.fx + 0.3 * tan_x,
                                                    (cam.width - cam.cx) / cam.fx + 0.3 * tan_x], rtol=1e-6)
        np.testing.assert_array_equal(row["background"], np.float32(bg))
