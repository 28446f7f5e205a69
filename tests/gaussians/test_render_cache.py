"""RenderCache: the static Gaussians' per-camera work kept between renders gives the full render's images,
bit for bit (random scenes, moving Gaussians crossing tiles, depth ties, moved cameras, backgrounds, many
worlds sharing the static part, and whole twins)."""

from __future__ import annotations

import numpy as np
import pytest

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import GaussianCloud, SplitGaussians
from twinbench.gaussians.render import RenderCache, render_batch


def _cam(eye=(0.9, -0.7, 0.6), target=(0.0, 0.0, 0.0), width=83, height=61, fx=70.0) -> Camera:
    return Camera.look_at(eye, target, fx=fx, width=width, height=height)


def _assert_same(a, b) -> None:
    np.testing.assert_array_equal(a.rgb, b.rgb)
    np.testing.assert_array_equal(a.depth, b.depth)
    np.testing.assert_array_equal(a.alpha, b.alpha)


def _full(static: GaussianCloud, moving: GaussianCloud, cam, bg=(0.1, 0.2, 0.3), threads=1):
    whole = GaussianCloud.concatenate([static, moving])
    return render_batch([(whole, cam)], background=bg, backend="warp", threads=threads)[0]


def _moved(cloud: GaussianCloud, shift) -> GaussianCloud:
    out = cloud.copy()
    out.means = out.means + np.asarray(shift, np.float32)
    return out


def test_static_camera_over_frames_with_gaussians_crossing_tiles(make_cloud):
    """A static camera over six frames: moving Gaussians sweep across the image (entering tiles, leaving
    them, one frame off screen); every frame equals the full render, the static work is built once."""
    static = make_cloud(900, degree=2, anisotropic=True, seed=1, spread=0.4, log_scale=(-4.0, -2.0))
    moving = make_cloud(120, degree=1, seed=2, spread=0.08, log_scale=(-3.5, -2.5))
    cam, bg = _cam(), (0.1, 0.2, 0.3)
    s_dev = static.to_device("cpu")
    cache = RenderCache()
    shifts = [(-0.4, 0, 0), (-0.2, 0.05, 0), (0.0, 0.1, 0.05), (0.2, 0.0, 0.1), (5.0, 0, 0), (0.3, -0.2, 0)]
    for k, shift in enumerate(shifts):
        m = _moved(moving, shift)
        for threads in (1, 2):
            got = render_batch([(SplitGaussians(s_dev, m.to_device("cpu")), cam)], background=bg,
                               backend="warp", threads=threads, cache=cache)[0]  # fmt: skip
            _assert_same(got, _full(static, m, cam, bg))
        assert (cache.builds, cache.misses) == (1, 1) and cache.hits == 2 * k
    # the moving Gaussians changed some tiles and not others, so both paths ran
    off = _full(static, _moved(moving, (5.0, 0, 0)), cam, bg)
    on = _full(static, moving, cam, bg)
    assert (on.rgb != off.rgb).any() and (on.rgb == off.rgb).any()


def test_depth_ties_put_the_static_gaussian_first(make_cloud):
    """Moving Gaussians at exactly a static Gaussian's position (equal depth), with other colours: the
    full render's order (depth, then index: static first) is kept, so the images match, and the order
    matters (the other order gives another image)."""
    static = make_cloud(300, seed=3, spread=0.3, log_scale=(-3.0, -2.0))
    twins = static.subset(np.arange(0, 300, 3))
    twins.sh = np.random.default_rng(4).normal(scale=1.0, size=twins.sh.shape).astype(np.float32)
    twins.logit_opacities = np.full(len(twins), 1.0, np.float32)
    # ties among the moving ones too: two copies of each, the second one red
    red = twins.copy()
    red.sh[:, 0] = (np.array([1.0, 0.0, 0.0]) - 0.5) / 0.28209479177387814
    moving = GaussianCloud.concatenate([twins, red])
    cam, bg = _cam(), (0.0, 0.0, 0.0)
    cache, s_dev, m_dev = RenderCache(), static.to_device("cpu"), moving.to_device("cpu")
    for _ in range(3):
        got = render_batch([(SplitGaussians(s_dev, m_dev), cam)], background=bg, cache=cache)[0]
        _assert_same(got, _full(static, moving, cam, bg))
    assert cache.hits == 1
    swapped = render_batch([(GaussianCloud.concatenate([moving, static]), cam)], background=bg)[0]
    assert np.abs(swapped.rgb - got.rgb).max() > 1e-3


def test_moved_camera_background_and_static_set_make_new_entries(make_cloud):
    """The kept work belongs to one (static cloud, camera, background): a moved or re-focused camera, a
    new background or another static cloud is rendered in full first, then kept; a camera that moves
    every frame is never kept; after writing into the static arrays, clear() forgets the kept work."""
    static = make_cloud(500, degree=1, anisotropic=True, seed=5, spread=0.35)
    moving = make_cloud(80, seed=6, spread=0.1)
    s_dev, m_dev = static.to_device("cpu"), moving.to_device("cpu")
    cache = RenderCache()

    def check(cam, bg, s=static, sd=s_dev):
        got = render_batch([(SplitGaussians(sd, m_dev), cam)], background=bg, cache=cache)[0]
        _assert_same(got, _full(s, moving, cam, bg))

    for cam, bg in [(_cam(), (0.1, 0.2, 0.3)), (_cam(eye=(0.9, -0.7, 0.61)), (0.1, 0.2, 0.3)),
                    (_cam(fx=71.0), (0.1, 0.2, 0.3)), (_cam(), (0.3, 0.2, 0.1))]:  # fmt: skip
        before = cache.builds
        check(cam, bg)
        check(cam, bg)
        check(cam, bg)
        assert cache.builds == before + 1
    for k in range(4):  # a camera on the move: full renders only
        check(_cam(eye=(0.9, -0.7 + 0.01 * k, 0.6)), (0.1, 0.2, 0.3))
    assert cache.builds == 4
    other = _moved(static, (0.0, 0.0, 0.02))
    o_dev = other.to_device("cpu")
    for _ in range(2):
        check(_cam(), (0.1, 0.2, 0.3), other, o_dev)
    assert cache.builds == 5
    s_dev.means.assign(other.means)  # written in place: the same arrays, other contents
    cache.clear()
    check(_cam(), (0.1, 0.2, 0.3), other, s_dev)
    check(_cam(), (0.1, 0.2, 0.3), other, s_dev)


def test_worlds_share_the_static_work_and_other_backends_render_the_concatenation(make_cloud, ref_render):
    """Many worlds: each its own moving Gaussians over one shared static cloud and camera, plus a camera
    on the move per world: one entry serves every world, on one thread or two, every image equal to its
    full render. A backend without a cache renders [static | moving]."""
    static = make_cloud(600, degree=1, anisotropic=True, seed=7, spread=0.35)
    s_dev = static.to_device("cpu")
    fixed, bg = _cam(), (0.2, 0.2, 0.2)
    cache = RenderCache()
    for step in range(3):
        worlds = [_moved(make_cloud(60, seed=10 + w, spread=0.1), (0.05 * step, 0, 0)) for w in range(4)]
        views = []
        for w, m in enumerate(worlds):
            split = SplitGaussians(s_dev, m.to_device("cpu"))
            views += [(split, fixed), (split, _cam(eye=(0.5 + 0.1 * w, -0.9, 0.4 + 0.05 * step), width=40))]
        outs = render_batch(views, background=bg, threads=1 + step % 2, cache=cache)
        for (_, cam), m, got in zip(views, [m for m in worlds for _ in (0, 1)], outs, strict=True):
            _assert_same(got, _full(static, m, cam, bg))
    assert cache.builds == 1 and cache.hits == 2 + 4 + 4  # built for the second world of the first call
    small = make_cloud(40, seed=20, spread=0.3)
    more = make_cloud(30, seed=21, spread=0.3)
    split = SplitGaussians(small.to_device("cpu"), more.to_device("cpu"))
    got = render_batch([(split, fixed)], background=bg, backend="reference")[0]
    want = ref_render(GaussianCloud.concatenate([small, more]), fixed, bg)
    assert np.abs(got.rgb - want[0]).max() < 1e-5


@pytest.mark.parametrize(
    "task", ["push-t", pytest.param("rope-routing", marks=pytest.mark.slow),
             pytest.param("toy-packing", marks=pytest.mark.slow)],
)  # fmt: skip
def test_twin_renders_equal_full_renders(task):
    """Every task's `fast` twin (push-T in the default suite), stepped by its expert: each step's images
    (both cameras: the front one from the cache, the wrist one in full while the arm moves) equal a full
    render of the same state."""
    from twinbench.evaluation.rollout import policy_observation
    from twinbench.tasks import get_task

    env = get_task(task).make_env(preset="fast")
    obs, info = env.reset(seed=0)
    expert = get_task(task).make_expert(env)
    twin, state = env.unwrapped.twin, env.unwrapped.state
    cache = twin.render_cache
    for _ in range(2):
        obs, _, _, _, info = env.step(expert.select_action(policy_observation(expert, obs, info)))
        cached = twin.render(state)
        twin.render_cache = None
        full = twin.render(state)
        twin.render_cache = cache
        for name in full:
            _assert_same(cached[name], full[name])
    assert cache.hits >= 3  # the front camera's renders came from the cache


@pytest.mark.gpu
def test_cache_on_cuda_equals_full_render_on_cuda_and_cpu(make_cloud):
    """On CUDA: the kept arrays live on the GPU; cached frames equal CUDA full renders (radix sorts: the
    same (tile, depth, index) order) bit for bit, and CPU renders within 1e-4; a moving camera and several
    worlds in one call (the batch path for the full renders) too."""
    static = make_cloud(900, degree=2, anisotropic=True, seed=1, spread=0.4, log_scale=(-4.0, -2.0))
    moving = make_cloud(120, degree=1, seed=2, spread=0.08, log_scale=(-3.5, -2.5))
    cam, bg = _cam(), (0.1, 0.2, 0.3)
    s_dev = static.to_device("cuda:0")
    cache = RenderCache()
    for k, shift in enumerate([(-0.3, 0, 0), (0.0, 0.1, 0.05), (0.2, 0.0, 0.1), (0.3, -0.2, 0)]):
        m = _moved(moving, shift)
        split = SplitGaussians(s_dev, m.to_device("cuda:0"))
        mover = _cam(eye=(0.9, -0.7 + 0.02 * k, 0.6), width=40)
        got = render_batch([(split, cam), (split, mover), (split, cam)], background=bg, cache=cache,
                           backend="warp")  # fmt: skip
        whole = GaussianCloud.concatenate([static, m])
        for out, c in zip(got, (cam, mover, cam), strict=True):
            full = render_batch([(whole.to_device("cuda:0"), c)], background=bg, backend="warp")[0]
            _assert_same(out, full)
            cpu = render_batch([(whole, c)], background=bg, backend="warp", device="cpu")[0]
            assert np.abs(out.rgb - cpu.rgb).max() < 1e-4
    assert cache.builds == 1 and cache.hits >= 6
    kept = next(iter(cache._kept.values()))
    assert str(kept.image.rgb.device) == "cuda:0" and str(kept.bins.records.device) == "cuda:0"


def test_split_gaussians_whole_is_read_instead_of_a_copy(make_cloud, monkeypatch):
    """SplitGaussians.whole (the caller's one-cloud copy, as a twin's world segment) serves full renders on
    the batch path and other backends without concatenating; a whole of another size is refused."""
    from twinbench.gaussians.cloud import DeviceGaussians
    from twinbench.gaussians.warp_raster import _render_warp_batch, _whole

    static, moving = make_cloud(200, seed=30, spread=0.3), make_cloud(50, seed=31, spread=0.2)
    whole = GaussianCloud.concatenate([static, moving]).to_device("cpu")
    split = SplitGaussians(whole.segment(0, 200), whole.segment(200, 50), whole)

    def no_copy(items):
        raise AssertionError("concatenated although `whole` was given")

    monkeypatch.setattr(DeviceGaussians, "concatenate", staticmethod(no_copy))
    assert _whole(split) is whole
    got = _render_warp_batch([(_whole(split), _cam())], np.zeros(3, np.float32))[0]
    _assert_same(got, render_batch([(split, _cam())], backend="warp")[0])
    with pytest.raises(ValueError, match="whole has 250 Gaussians, not 249"):
        SplitGaussians(whole.segment(0, 200), whole.segment(200, 49), whole)


def test_cuda_path_run_on_cpu_cached_batch_equals_full_batch(make_cloud, ref_render):
    """The CUDA path of cached views run on CPU (one launch per stage for every cached view, the per-pixel
    kernel): views of two cameras over three worlds (moving parts of one cloud, one world's moving part off
    screen) equal full batch renders with the same kernel bit for bit, full renders with the CPU's tile
    kernel within a level (and within 1e-5 nearly everywhere), and the brute-force reference."""
    from twinbench.gaussians.warp_raster import _Kept, _render_kept_batch, _render_warp_batch

    static = make_cloud(900, degree=2, anisotropic=True, seed=1, spread=0.4, log_scale=(-4.0, -2.0))
    moving = make_cloud(120, degree=1, seed=2, spread=0.08, log_scale=(-3.5, -2.5))
    cams, bg = [_cam(), _cam(eye=(-0.8, -0.9, 0.7), width=50, height=40, fx=45.0)], (0.1, 0.2, 0.3)
    worlds = [_moved(moving, s) for s in ((-0.2, 0.0, 0.0), (0.1, 0.1, 0.05), (5.0, 0.0, 0.0))]
    s_dev = static.to_device("cpu")
    m_all = GaussianCloud.concatenate(worlds).to_device("cpu")
    m_dev = [m_all.segment(120 * w, 120) for w in range(3)]
    kept = [_Kept(s_dev, cam, np.asarray(bg, np.float32), 1, per_pixel=True) for cam in cams]
    items = [(kept[c], m_dev[w], cams[c]) for w in range(3) for c in range(2)]
    got = _render_kept_batch(items, np.asarray(bg, np.float32), per_pixel=True)
    wholes = [GaussianCloud.concatenate([static, m]) for m in worlds]
    jobs = [(wholes[w].to_device("cpu"), cams[c]) for w in range(3) for c in range(2)]
    full = _render_warp_batch(jobs, np.asarray(bg, np.float32), per_pixel=True)
    tiles = _render_warp_batch(jobs, np.asarray(bg, np.float32), per_pixel=False)
    for a, b, t in zip(got, full, tiles, strict=True):
        _assert_same(a, b)
        assert np.abs(a.rgb - t.rgb).max() <= 1.0 / 255 and np.abs(a.alpha - t.alpha).max() <= 1.0 / 255
        assert np.mean(np.abs(a.rgb - t.rgb) > 1e-5) < 1e-3
    rgb, _, alpha = ref_render(wholes[0], cams[0], bg)
    assert np.abs(got[0].rgb - rgb).max() < 2e-3 and np.abs(got[0].alpha - alpha).max() < 2e-3
    # the moving Gaussians reached some pixels of world 0's first view and not others; world 2's are off
    # screen, so its views are the kept images
    alone = render_batch([(static, cams[0])], background=bg, backend="warp")[0]
    assert (np.abs(got[0].rgb - alone.rgb) > 1e-3).any() and (got[0].rgb == full[0].rgb).all()
    np.testing.assert_array_equal(got[4].rgb, kept[0].image.rgb.numpy().reshape(got[4].rgb.shape))
    # depth ties: moving copies of static Gaussians (other colours) keep the full render's order
    twins = static.subset(np.arange(0, 900, 3))
    twins.sh = np.random.default_rng(4).normal(scale=1.0, size=twins.sh.shape).astype(np.float32)
    bg32 = np.asarray(bg, np.float32)
    tie = _render_kept_batch([(kept[0], twins.to_device("cpu"), cams[0])], bg32, per_pixel=True)[0]
    whole = GaussianCloud.concatenate([static, twins]).to_device("cpu")
    _assert_same(tie, _render_warp_batch([(whole, cams[0])], bg32, per_pixel=True)[0])
    # nothing moving: the kept image
    nothing = twins.subset(np.arange(0)).to_device("cpu")
    still = _render_kept_batch([(kept[1], nothing, cams[1])], bg32, per_pixel=True)[0]
    _assert_same(still, _render_warp_batch([(s_dev, cams[1])], bg32, per_pixel=True)[0])


def test_moving_cameras_cull_the_static_part_a_chunk_at_a_time(make_cloud, monkeypatch):
    """A moving camera's full renders of a SplitGaussians with a cache cull the static part by chunks of
    Gaussians in spatial order (`RenderCache.balls`): close-ups, views across the near plane and views
    whose footprints reach in from beyond the image sides equal full renders of the concatenation bit for
    bit, and a close-up does cull most chunks whole."""
    import warp as wp

    from twinbench.gaussians import warp_raster as wr

    static = make_cloud(4000, degree=1, anisotropic=True, seed=5, spread=1.5, log_scale=(-4.5, -1.5))
    static = static.spatially_sorted()
    moving = make_cloud(60, seed=6, spread=0.05)
    s_dev, m_dev = static.to_device("cpu"), moving.to_device("cpu")
    bg = (0.2, 0.1, 0.0)
    passed = []  # the chunk bounds each projection of [static, moving] got, per part
    project = wr._project

    def spy(parts, cam, background, threads, balls=None):
        if len(parts) == 2:
            passed.append(balls)
        return project(parts, cam, background, threads, balls)

    monkeypatch.setattr(wr, "_project", spy)
    poses = [((0.3, 0.2, 0.25), (0.0, 0.0, 0.0), 90.0), ((0.05, 0.02, 0.0), (1.0, 0.3, 0.1), 60.0),
             ((2.5, 0.0, 0.0), (0.0, 0.0, 0.0), 120.0), ((1.4, 1.4, 1.4), (-1.0, -1.0, -1.0), 40.0),
             ((0.0, 0.0, 1.55), (0.0, 0.01, -1.0), 80.0)]  # fmt: skip
    for threads in (1, 2):
        cache = RenderCache()
        for eye, target, fx in poses:
            cam = Camera.look_at(eye, target, fx=fx, width=64, height=48)
            got = render_batch([(SplitGaussians(s_dev, m_dev), cam)], background=bg, backend="warp",
                               threads=threads, cache=cache)[0]  # fmt: skip
            _assert_same(got, _full(static, moving, cam, bg))
        assert cache.builds == 0 and len(cache._balls) == 1  # every view a full render, the bounds made once
    # each full render's static part was projected with the kept bounds (the moving part without)
    kept = cache.balls(s_dev)
    assert len(passed) == 2 * len(poses) and all(b is not None and b[0] is not None and b[1] is None
                                                 for b in passed)
    assert passed[-1][0] is kept and len(kept.balls) == -(-len(static) // 32)

    @wp.kernel
    def outside(views: wp.array(dtype=wr._View), balls: wp.array(dtype=wp.vec4),
                scale: wp.array(dtype=wp.float32), out: wp.array(dtype=wp.int32)):
        c = wp.tid()
        if wr._chunk_outside(views[0], balls[c], scale[c], wr.NEAR):
            out[c] = 1

    dense = make_cloud(30000, seed=7, spread=1.5, log_scale=(-5.5, -4.5)).spatially_sorted().to_device("cpu")
    balls = RenderCache().balls(dense)
    close = Camera.look_at(*poses[0][:2], fx=poses[0][2], width=64, height=48)
    out = wp.zeros(balls.balls.shape[0], dtype=wp.int32, device="cpu")
    wp.launch(outside, dim=len(out), inputs=[wr._views([(close, bg, 0, 0, 0, 0)], "cpu"), balls.balls,
                                             balls.scale], outputs=[out], device="cpu")
    assert out.numpy().mean() > 0.4  # (0.47: behind the camera, beyond the sides)
