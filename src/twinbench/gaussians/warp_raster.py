"""The Warp tile rasteriser (CPU and CUDA): the "warp" renderer backend.

Math (DESIGN §6, see render_rules): EWA projection with a 0.3 px low-pass added to the 2D covariance, 16x16
tiles, front-to-back compositing by camera depth, alpha = min(0.99, o exp(-d^2/2)), skip alpha < 1/255, stop
a pixel before the Gaussian that would bring its transmittance below 1e-4. Gaussians with z < near are
culled. A Gaussian's footprint is the bounding box of the ellipse where alpha >= 1/255
(d^2 <= 2 ln(255 o), at most 3.33 sigma), so tile culling drops nothing the compositing would keep.
The Jacobian clamps x/z, y/z to 0.3 tan(fov/2) beyond the image (as gsplat does); SH colours are
max(0, 0.5 + sum c_k Y_k(d)) with d the unit direction from the camera centre; rgb is clipped to [0, 1].

Pipeline: project (packed 64-byte record per Gaussian; a Gaussian whose footprint bound misses the image is
culled before its covariance is formed; a CPU thread takes 32 Gaussians, and where the cloud is a
RenderCache's static part, culls all 32 at once when a ball around them lies beyond the near plane or an
image side widened by their footprint bound) -> stable depth sort (equal depths
in index order) -> (tile, Gaussian) pairs in depth order -> stable sort by tile -> records gathered into
pair order -> one thread per tile walks its Gaussians front to back; for each row of a Gaussian's footprint
in the tile, the row's 16 pixels are composited at once by native code the compiler vectorises
(`_composite_rows`: o exp(-d^2/2) at each pixel, exp within 2 ulp of expf; stopped pixels masked) into the
tile's own accumulators, written to the image once at the end; rows whose footprint pixels have all stopped
(per-row bitmasks), Gaussians whose rows have all stopped and the tile once every pixel has stopped are
skipped. CPU threads come from one pool, started once (gaussians/threads.py); a thread out of views helps
rasterise the last views' tiles (WorkBoard; the views before them rasterise in one launch each). On CPU
the pair sorts run in NumPy; on CUDA (`_render_warp_batch`) they are Warp radix sorts (the same order), a
batch of views (every camera of every world) runs each stage once for all of them, and the last stage is
one thread per pixel walking its tile's list with o exp(-d^2/2) at the pixel (`_rasterise_pixels`: a tile
per thread leaves a GPU idle; 240x240 images have 225 tiles): CUDA images agree with CPU ones within a
level (alpha within a few ulp), not bit for bit.

Static/moving split (`RenderCache`, `SplitGaussians(static, moving)`): for a camera that has not moved,
the static part's records, (tile, depth)-ordered pair lists and the image it makes alone are kept (on the
render's device, shared by every view of that camera, e.g. many worlds); a render projects and bins only
the moving part, rasterises only the tiles its pairs reach, merging the two lists by depth (static first
on equal depths: the full render's order), and copies the kept pixels of every other tile. The images
equal a full render of [static | moving] on the same device bit for bit. On CUDA the cached views of a
call run as one batch (`_render_kept_batch`), but the cache saves little there: projecting and sorting
the static Gaussians is ~0.1 ms of GPU time, and a render's cost is its launches and read-backs (push-T's
two cameras, one world, H100: 3.4 ms cached, 3.2 ms in full), so twins keep it on CPU only.
"""

from __future__ import annotations

import ctypes
import functools
import threading
from collections import OrderedDict

import numpy as np
import warp as wp

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud, SplitGaussians
from twinbench.gaussians.render_rules import ALPHA_MAX, ALPHA_MIN, LOW_PASS, NEAR, T_MIN, TILE, RenderOutput
from twinbench.gaussians.threads import WorkBoard, launch_split, run_threads

wp.set_module_options({"enable_backward": False})


# ----- Warp kernels ---------------------------------------------------------------------------------
# One 64-byte record per projected Gaussian (a single cache line per Gaussian-tile pair):
# u, v, conic a, b, c, extent x, y, r, g, b, depth, opacity, d2max = 2 ln(255 o), 1 / a, -, -
vec16 = wp.types.vector(length=16, dtype=wp.float32)
vec16i = wp.types.vector(length=16, dtype=wp.int32)  # a tile's 16 rows of pixel bits


@wp.func
def _quat_wxyz_to_mat(q: wp.vec4):
    w = q[0]
    x = q[1]
    y = q[2]
    z = q[3]
    return wp.mat33(
        1.0 - 2.0 * (y * y + z * z),
        2.0 * (x * y - w * z),
        2.0 * (x * z + w * y),
        2.0 * (x * y + w * z),
        1.0 - 2.0 * (x * x + z * z),
        2.0 * (y * z - w * x),
        2.0 * (x * z - w * y),
        2.0 * (y * z + w * x),
        1.0 - 2.0 * (x * x + y * y),
    )


@wp.func
def _sh_colour(sh: wp.array2d(dtype=wp.vec3), i: int, k: int, d: wp.vec3):
    c = 0.28209479177387814 * sh[i, 0]
    if k > 1:
        x = d[0]
        y = d[1]
        z = d[2]
        c = c - 0.4886025119029199 * y * sh[i, 1] + 0.4886025119029199 * z * sh[i, 2]
        c = c - 0.4886025119029199 * x * sh[i, 3]
        if k > 4:
            xx = x * x
            yy = y * y
            zz = z * z
            c = c + 1.0925484305920792 * x * y * sh[i, 4] - 1.0925484305920792 * y * z * sh[i, 5]
            c = c + 0.31539156525252005 * (2.0 * zz - xx - yy) * sh[i, 6]
            c = c - 1.0925484305920792 * x * z * sh[i, 7] + 0.5462742152960396 * (xx - yy) * sh[i, 8]
            if k > 9:
                c = c - 0.5900435899266435 * y * (3.0 * xx - yy) * sh[i, 9]
                c = c + 2.890611442640554 * x * y * z * sh[i, 10]
                c = c - 0.4570457994644658 * y * (4.0 * zz - xx - yy) * sh[i, 11]
                c = c + 0.3731763325901154 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[i, 12]
                c = c - 0.4570457994644658 * x * (4.0 * zz - xx - yy) * sh[i, 13]
                c = c + 1.445305721320277 * z * (xx - yy) * sh[i, 14]
                c = c - 0.5900435899266435 * x * (xx - 3.0 * yy) * sh[i, 15]
    c = c + wp.vec3(0.5, 0.5, 0.5)
    return wp.vec3(wp.max(c[0], 0.0), wp.max(c[1], 0.0), wp.max(c[2], 0.0))


@wp.struct
class _View:
    """One view of a batch: its camera, and where its Gaussians, records, tiles and pixels start."""

    rot_wc: wp.mat33
    t_wc: wp.vec3
    cam_pos: wp.vec3
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    lim: wp.vec4  # Jacobian clamp: x below, x above, y below, y above (tan units)
    src: int  # first Gaussian of the view's cloud in the batch's cloud
    item: int  # first record of the view (records: one per Gaussian per view)
    tile: int  # first tile of the view
    tiles_x: int
    pixel: int  # first pixel of the view's image in the batch's images
    background: wp.vec3


@wp.func
def _view_of(views: wp.array(dtype=_View), k: int, field: int):
    """The last view whose first record (field 0), first tile (field 1) or first pixel (field 2) is <= k
    (binary search)."""
    lo = int(0)  # noqa: UP018 (a Warp dynamic variable)
    hi = views.shape[0] - 1
    while lo < hi:
        mid = (lo + hi + 1) // 2
        start = views[mid].item
        if field == 1:
            start = views[mid].tile
        elif field == 2:
            start = views[mid].pixel
        if start <= k:
            lo = mid
        else:
            hi = mid - 1
    return lo


_D2MAX_BOUND = 11.0827  # > 2 ln 255, the largest d2max (opacity 1)
_CHUNK = 32  # Gaussians a CPU projection thread takes in turn (its view looked up once)


@wp.func
def _project_one(
    out: int,
    vw: _View,
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=wp.float32),
    sh: wp.array2d(dtype=wp.vec3),
    sh_k: int,
    near: float,
    record: wp.array(dtype=vec16),
    depth: wp.array(dtype=wp.float32),
    rect: wp.array(dtype=wp.vec4i),
    n_tiles: wp.array(dtype=wp.int32),
):
    """Record `out`: Gaussian vw.src + out - vw.item of the cloud seen by view `vw` -> packed record,
    depth, tile rectangle, tile count (0 and depth 3e38 when culled)."""
    i = vw.src + out - vw.item
    n_tiles[out] = 0
    depth[out] = 3.0e38
    p = vw.rot_wc * means[i] + vw.t_wc
    z = p[2]
    o = opacities[i]
    if z < near or o < ALPHA_MIN:
        return
    # frustum cull before the covariance: the footprint's half extent sqrt(d2max (J Sigma J^T + low pass))
    # is at most r below (|J|_F^2 s_max^2 bounds the projected covariance), plus a pixel for rounding
    s = scales[i]
    txz = wp.clamp(p[0] / z, -vw.lim[0], vw.lim[1])
    tyz = wp.clamp(p[1] / z, -vw.lim[2], vw.lim[3])
    smax = wp.max(s[0], wp.max(s[1], s[2]))
    jf2 = (vw.fx * vw.fx * (1.0 + txz * txz) + vw.fy * vw.fy * (1.0 + tyz * tyz)) / (z * z)
    uc = vw.fx * p[0] / z + vw.cx
    vc = vw.fy * p[1] / z + vw.cy
    # most culled Gaussians go by a first test without log or sqrt: d2max <= 2 ln 255 (o <= 1) and
    # (sqrt(A) + 1)^2 <= 2 A + 2
    off = wp.max(wp.max(-uc, uc - float(vw.width)), wp.max(-vc, vc - float(vw.height)))
    if o <= 1.0 and off > 0.0 and off * off > 2.0 * _D2MAX_BOUND * (jf2 * smax * smax + LOW_PASS) + 2.0:
        return
    r = wp.sqrt(2.0 * wp.log(o / ALPHA_MIN) * (jf2 * smax * smax + LOW_PASS)) + 1.0
    if uc + r < 0.0 or vc + r < 0.0 or uc - r > float(vw.width) or vc - r > float(vw.height):
        return
    q = quats[i]
    qn = wp.length(q)
    if qn > 0.0:
        q = q / qn
    m = _quat_wxyz_to_mat(q) * wp.diag(s)
    cov_w = m * wp.transpose(m)
    cov_c = vw.rot_wc * cov_w * wp.transpose(vw.rot_wc)
    tx = wp.clamp(p[0] / z, -vw.lim[0], vw.lim[1]) * z
    ty = wp.clamp(p[1] / z, -vw.lim[2], vw.lim[3]) * z
    j = wp.mat33(vw.fx / z, 0.0, -vw.fx * tx / (z * z), 0.0, vw.fy / z, -vw.fy * ty / (z * z), 0.0, 0.0, 0.0)
    c2 = j * cov_c * wp.transpose(j)
    a = c2[0, 0] + LOW_PASS
    b = c2[0, 1]
    c = c2[1, 1] + LOW_PASS
    det = a * c - b * b
    if det <= 0.0:
        return
    u = vw.fx * p[0] / z + vw.cx
    v = vw.fy * p[1] / z + vw.cy
    d2max = 2.0 * wp.log(o / ALPHA_MIN)
    ex = wp.sqrt(d2max * a)
    ey = wp.sqrt(d2max * c)
    # pixel centres i + 0.5 inside [u - ex, u + ex]
    px0 = wp.max(int(wp.ceil(u - ex - 0.5)), 0)
    px1 = wp.min(int(wp.floor(u + ex - 0.5)), vw.width - 1)
    py0 = wp.max(int(wp.ceil(v - ey - 0.5)), 0)
    py1 = wp.min(int(wp.floor(v + ey - 0.5)), vw.height - 1)
    if px0 > px1 or py0 > py1:
        return
    tx0 = px0 / 16
    tx1 = px1 / 16
    ty0 = py0 / 16
    ty1 = py1 / 16
    col = _sh_colour(sh, i, sh_k, wp.normalize(means[i] - vw.cam_pos))
    rec = vec16()
    rec[0] = u
    rec[1] = v
    rec[2] = c / det
    rec[3] = -b / det
    rec[4] = a / det
    rec[5] = ex
    rec[6] = ey
    rec[7] = col[0]
    rec[8] = col[1]
    rec[9] = col[2]
    rec[10] = z
    rec[11] = o
    rec[12] = d2max
    rec[13] = det / c
    record[out] = rec
    depth[out] = z
    rect[out] = wp.vec4i(tx0, ty0, tx1, ty1)
    n_tiles[out] = (tx1 - tx0 + 1) * (ty1 - ty0 + 1)


@wp.func
def _chunk_outside(vw: _View, ball: wp.vec4, smax: float, near: float):
    """Whether `_project_one` culls every Gaussian of a chunk whose centres lie in `ball` (centre, radius)
    and whose scales are at most `smax` in magnitude, opacities at most 1 (smax < 0: unknown, keep it):
    the ball lies wholly before the near plane, or wholly beyond an image side widened by a footprint
    bound that holds for all of them (smax at the ball's nearest depth, the Jacobian's clamp, d2max <= 2 ln
    255) plus a pixel of slack over the per-Gaussian test's own."""
    if smax < 0.0:
        return False
    rho = ball[3]
    p = vw.rot_wc * wp.vec3(ball[0], ball[1], ball[2]) + vw.t_wc
    if p[2] + rho + 1.0e-5 < near:
        return True
    zmin = p[2] - rho
    if zmin < near:
        return False
    lx = wp.max(vw.lim[0], vw.lim[1])
    ly = wp.max(vw.lim[2], vw.lim[3])
    jf2 = (vw.fx * vw.fx * (1.0 + lx * lx) + vw.fy * vw.fy * (1.0 + ly * ly)) / (zmin * zmin)
    r = wp.sqrt(_D2MAX_BOUND * (jf2 * smax * smax + LOW_PASS)) + 2.0
    # u < -r: fx x + (cx + r) z < 0; u > width + r: fx x - (width + r - cx) z > 0; v likewise
    kl = vw.cx + r
    kr = float(vw.width) + r - vw.cx
    kt = vw.cy + r
    kb = float(vw.height) + r - vw.cy
    return (
        vw.fx * p[0] + kl * p[2] < -rho * wp.sqrt(vw.fx * vw.fx + kl * kl)
        or vw.fx * p[0] - kr * p[2] > rho * wp.sqrt(vw.fx * vw.fx + kr * kr)
        or vw.fy * p[1] + kt * p[2] < -rho * wp.sqrt(vw.fy * vw.fy + kt * kt)
        or vw.fy * p[1] - kb * p[2] > rho * wp.sqrt(vw.fy * vw.fy + kb * kb)
    )


@wp.kernel
def _preprocess(
    means: wp.array(dtype=wp.vec3),
    quats: wp.array(dtype=wp.vec4),
    scales: wp.array(dtype=wp.vec3),
    opacities: wp.array(dtype=wp.float32),
    sh: wp.array2d(dtype=wp.vec3),
    sh_k: int,
    views: wp.array(dtype=_View),
    near: float,
    chunk: int,
    offset: int,
    end: int,
    balls: wp.array(dtype=wp.vec4),
    ball_scale: wp.array(dtype=wp.float32),
    chunk0: int,
    record: wp.array(dtype=vec16),
    depth: wp.array(dtype=wp.float32),
    rect: wp.array(dtype=wp.vec4i),
    n_tiles: wp.array(dtype=wp.int32),
):
    """Records [offset + chunk t', + chunk) below `end` (t' = chunk0 + thread), each seen by its view: one
    thread per `chunk` records (_CHUNK on CPU, where a thread per record cost more than its culled
    records' own work; 1 on CUDA), the view looked up once when the chunk lies in one view. With `balls`
    (one per chunk of the part, and its largest scale: see _ChunkBalls), a chunk `_chunk_outside` the
    view is culled whole."""
    c = wp.tid() + chunk0
    first = offset + c * chunk
    last = wp.min(first + chunk, end)
    k = _view_of(views, first, 0)
    vw = views[k]
    if k == _view_of(views, last - 1, 0):
        if c < balls.shape[0] and _chunk_outside(vw, balls[c], ball_scale[c], near):
            for out in range(first, last):
                n_tiles[out] = 0
                depth[out] = 3.0e38
            return
        for out in range(first, last):
            _project_one(out, vw, means, quats, scales, opacities, sh, sh_k, near, record, depth, rect,
                         n_tiles)
    else:
        for out in range(first, last):
            _project_one(out, views[_view_of(views, out, 0)], means, quats, scales, opacities, sh, sh_k, near,
                         record, depth, rect, n_tiles)


@wp.kernel
def _emit_pairs(
    order: wp.array(dtype=wp.int32),
    offsets: wp.array(dtype=wp.int32),
    rect: wp.array(dtype=wp.vec4i),
    n_tiles: wp.array(dtype=wp.int32),
    views: wp.array(dtype=_View),
    chunk: int,
    start: int,
    keys: wp.array(dtype=wp.int32),
    values: wp.array(dtype=wp.int32),
):
    """Entries [chunk t, chunk (t + 1)) of the depth-ordered list (t = tid + start; a CPU thread takes a
    chunk) write (tile id, record id) for each tile their box touches; tile ids count the views' tiles one
    view after another."""
    r0 = (wp.tid() + start) * chunk
    for r in range(r0, wp.min(r0 + chunk, order.shape[0])):
        g = order[r]
        if n_tiles[g] > 0:
            vw = views[_view_of(views, g, 0)]
            n = offsets[r] - n_tiles[g]
            rc = rect[g]
            for ty in range(rc[1], rc[3] + 1):
                for tx in range(rc[0], rc[2] + 1):
                    keys[n] = vw.tile + ty * vw.tiles_x + tx
                    values[n] = g
                    n += 1


@wp.kernel
def _init_depth_sort(
    depth: wp.array(dtype=wp.float32), keys: wp.array(dtype=wp.float32), ids: wp.array(dtype=wp.int32)
):
    """Radix-sort input: keys = depths, values = Gaussian ids 0..n-1 (no host upload per frame)."""
    i = wp.tid()
    keys[i] = depth[i]
    ids[i] = i


@wp.kernel
def _gather_counts(
    order: wp.array(dtype=wp.int32), n_tiles: wp.array(dtype=wp.int32), out: wp.array(dtype=wp.int32)
):
    r = wp.tid()
    out[r] = n_tiles[order[r]]


@wp.kernel
def _tile_ranges(keys: wp.array(dtype=wp.int32), count: int, ranges: wp.array(dtype=wp.vec2i)):
    """Start/end of each tile's run in the tile-sorted pair list (Warp does not short-circuit `or`).
    The first and the last pair of a run are different threads: each stores only its own component
    (a whole-vector read-modify-write would race on CUDA)."""
    n = wp.tid()
    tile = keys[n]
    first = n == 0
    if not first:
        first = keys[n - 1] != tile
    last = n == count - 1
    if not last:
        last = keys[n + 1] != tile
    if first:
        ranges[tile][0] = n
    if last:
        ranges[tile][1] = n + 1


@wp.kernel
def _gather_records(
    values: wp.array(dtype=wp.int32), record: wp.array(dtype=vec16), chunk: int, total: int, start: int,
    out: wp.array(dtype=vec16),
):
    """Pairs [chunk t, chunk (t + 1)) of `total` (t = tid + start) get their records copied into pair
    order (a CPU thread copies a chunk: a thread each cost more than the copy)."""
    n0 = (wp.tid() + start) * chunk
    for n in range(n0, wp.min(n0 + chunk, total)):
        out[n] = record[values[n]]


@wp.func
def _span(rec: vec16, y: int, gx0: int, gx1: int):
    """The columns [x, y] of row y that record `rec`'s ellipse d^2 <= d2max covers (alpha >= 1/255), widened
    by 1e-3 px so that rounding never drops a pixel the alpha test would keep (an empty span when x > y),
    clipped to [gx0, gx1]."""
    dy = float(y) + 0.5 - rec[1]
    disc = rec[3] * rec[3] * dy * dy - rec[2] * (rec[4] * dy * dy - rec[12])
    if disc < 0.0:
        return wp.vec2i(1, 0)
    half = wp.sqrt(disc) * rec[13] + 1.0e-3
    ctr = rec[0] - rec[3] * dy * rec[13]
    return wp.vec2i(wp.max(int(wp.ceil(ctr - half - 0.5)), gx0), wp.min(int(wp.floor(ctr + half - 0.5)), gx1))


@wp.func
def _bounds(rec: vec16, x0: int, y0: int, x1: int, y1: int):
    """Record `rec`'s pixel bounding box (x0, y0, x1, y1, inclusive) clipped to the tile [x0, x1) x
    [y0, y1)."""
    return wp.vec4i(
        wp.max(int(wp.ceil(rec[0] - rec[5] - 0.5)), x0),
        wp.max(int(wp.ceil(rec[1] - rec[6] - 0.5)), y0),
        wp.min(int(wp.floor(rec[0] + rec[5] - 0.5)), x1 - 1),
        wp.min(int(wp.floor(rec[1] + rec[6] - 0.5)), y1 - 1),
    )


@wp.func
def _merge_next(record: wp.array(dtype=vec16), na: int, ea: int, record_b: wp.array(dtype=vec16), nb: int,
                eb: int):
    """The next record of two depth-ordered lists [na, ea) and [nb, eb) merged (the first list's record
    first on equal depths), and both lists' next positions."""
    take_b = nb < eb
    if take_b and na < ea:
        take_b = record_b[nb][10] < record[na][10]
    if take_b:
        return record_b[nb], na, nb + 1
    return record[na], na + 1, nb


# The row steps of the CPU tile kernel, in native code so that the compiler vectorises them: for one
# Gaussian in one tile, each row of its footprint [ylo, yhi] whose footprint pixels (`box`) have not all
# stopped (`row_done`, per-row bits) has its 16 pixels composited at once (2.1x faster than a scalar loop
# over the footprint's columns; the loop over rows in native code too: 10 % less). Each pixel's alpha =
# min(ALPHA_MAX, o exp(-d^2 / 2)) evaluated at the pixel (exp: range reduction by ln 2 and the Cephes
# single-precision polynomial, within 2 ulp of expf), composited where alpha >= ALPHA_MIN, the pixel
# stopped where its transmittance would fall below T_MIN (stored negated, as the kernel's other stopped
# pixels). `acc` holds a tile's accumulators, a row every _ROW floats: transmittance, depth, r, g, b (16
# each). Returns `live_rows` without the rows whose every pixel has now stopped, and from bit 16 the count
# of pixels that stopped. Pure C++: it also compiles for CUDA (tests/gaussians checks with NVRTC).
# On a CPU with AVX-512 (Clang, as Warp compiles for the host) a row is one 512-bit vector: Clang prefers
# 256-bit vectors there unless a function uses 512-bit ones, which the (discarded) 512-bit builtin below
# declares, and the loop pragma asks for all 16 pixels at once: the tile step ~20 % faster than with
# 256-bit vectors on an Intel Xeon, the same images bit for bit; other CPUs (and CUDA) compile the plain loop.
# The exponent is floored at _EXP_FLOOR: below it alpha < ALPHA_MIN whatever the opacity (<= 1), so the
# floor changes no pixel, and o exp(floor) with o >= ALPHA_MIN (lower opacities are culled) stays a
# normal float. Without it the pixels far from a footprint's centre made subnormal alphas and products
# (e.g. exp(-87) o), which Intel cores compute in microcode: the tile step ran 2.3x slower there.
_EXP_FLOOR = -60.0
_ROW = 80  # floats a tile row takes in the accumulators
_ROW_SNIPPET = """
#if defined(__AVX512F__) && defined(__clang__) && !defined(__CUDACC__)
{  // marks the function as using 512-bit vectors: a tile row below is one register
    typedef float v16w __attribute__((ext_vector_type(16)));
    v16w zero = {};
    (void)__builtin_ia32_selectps_512((unsigned short)0, zero, zero);
}
#endif
int* done_rows = row_done.data + done0;
int ndone = 0;
for (int y = ylo; y <= yhi; ++y) {
    int done_bits = done_rows[y];
    if ((done_bits & box) == box) continue;  // every pixel of the footprint's row has stopped
    int mask = box & ~done_bits;
    float dy = ((float)y + 0.5f) - v;
    float* acc_row = acc.data + offset + (y - y0) * ROWf;
    int stopped = 0;
    int count = 0;
#if defined(__AVX512F__) && defined(__clang__) && !defined(__CUDACC__)
#pragma clang loop vectorize_width(16) interleave_count(1)
#endif
    for (int j = 0; j < 16; ++j) {
        float dx = ((float)(x0 + j) + 0.5f) - u;
        float d2 = ca * dx * dx + 2.0f * cbc * dx * dy + cc * dy * dy;
        float e = -0.5f * d2;
        e = e > EXP_FLOORf ? e : EXP_FLOORf;
        float n = rintf(e * 1.44269504088896341f);
        float r = fmaf(n, -0.693359375f, e);
        r = fmaf(n, 2.12194440e-4f, r);
        float p = 1.9875691500e-4f;
        p = fmaf(p, r, 1.3981999507e-3f);
        p = fmaf(p, r, 8.3334519073e-3f);
        p = fmaf(p, r, 4.1665795894e-2f);
        p = fmaf(p, r, 1.6666665459e-1f);
        p = fmaf(p, r, 5.0000001201e-1f);
        p = fmaf(p, r * r, r) + 1.0f;
        unsigned int sbits = ((unsigned int)((int)n + 127)) << 23;
        float scale;
        memcpy(&scale, &sbits, 4);
        float g = opacity * (p * scale);
        float alpha = g < alpha_max ? g : alpha_max;
        bool act = ((mask >> j) & 1) != 0 && alpha >= alpha_min;
        float tv = acc_row[j];
        float test = tv * (1.0f - alpha);
        bool stop = act && test < t_min;
        bool add = act && !(test < t_min);
        float w = alpha * tv;
        acc_row[16 + j] = add ? acc_row[16 + j] + w * z : acc_row[16 + j];
        acc_row[32 + j] = add ? acc_row[32 + j] + w * red : acc_row[32 + j];
        acc_row[48 + j] = add ? acc_row[48 + j] + w * green : acc_row[48 + j];
        acc_row[64 + j] = add ? acc_row[64 + j] + w * blue : acc_row[64 + j];
        acc_row[j] = stop ? -tv : (add ? test : tv);
        stopped |= stop ? (1 << j) : 0;
        count += stop ? 1 : 0;
    }
    if (stopped != 0) {
        ndone += count;
        done_bits |= stopped;
        done_rows[y] = done_bits;
        if ((done_bits & valid) == valid) live_rows &= ~(1 << (y - y0));
    }
}
return live_rows | (ndone << 16);
""".replace("EXP_FLOOR", repr(_EXP_FLOOR)).replace("ROWf", repr(_ROW))
_TILE_ACC = 16 * _ROW


@wp.func_native(_ROW_SNIPPET)
def _composite_rows(acc: wp.array(dtype=wp.float32), offset: int, row_done: wp.array(dtype=wp.int32),
                    done0: int, x0: int, y0: int, ylo: int, yhi: int, box: int, valid: int, live_rows: int,
                    u: float, v: float, ca: float, cbc: float, cc: float, opacity: float, red: float,
                    green: float, blue: float, z: float, alpha_max: float, alpha_min: float,
                    t_min: float) -> int: ...


_CLAIM_SNIPPET = """
#if defined(__CUDA_ARCH__)
return atomicAdd((int*)counter.data, 1);
#else
return __atomic_fetch_add((int*)counter.data, 1, __ATOMIC_RELAXED);
#endif
"""


@wp.func_native(_CLAIM_SNIPPET)
def _claim(counter: wp.array(dtype=wp.int32)) -> int:
    """The counter's value before adding 1, atomically (Warp's own atomic_add is a plain add on CPU,
    whose kernels it runs on one thread)."""
    ...


@wp.kernel
def _rasterise(
    tile_list: wp.array(dtype=wp.int32),
    claim: wp.array(dtype=wp.int32),
    ranges: wp.array(dtype=wp.vec2i),
    record: wp.array(dtype=vec16),
    ranges_b: wp.array(dtype=wp.vec2i),
    record_b: wp.array(dtype=vec16),
    views: wp.array(dtype=_View),
    out_rgb: wp.array(dtype=wp.vec3),
    out_depth: wp.array(dtype=wp.float32),
    out_t: wp.array(dtype=wp.float32),
    row_done: wp.array(dtype=wp.int32),
    acc: wp.array(dtype=wp.float32),
):
    """One thread per tile of `tile_list` (every view's tiles when it is empty), Gaussian-major: each Gaussian
    (records in pair order, by depth within the tile) updates the pixels of its footprint in the tile, a row
    at a time (`_composite_rows`), in the tile's accumulators (`acc`, _TILE_ACC floats per thread index). A
    second list (`ranges_b`, `record_b`; none when `ranges_b` is empty: a full render) is merged in by depth,
    the first list's record first on equal depths: with the static Gaussians first and the moving ones second,
    the order of a full render of [static | moving] (by depth, then index). With a second list the output
    arrays come holding the first list's own image, and only the pixels some record of the second list's spans
    reaches are composited again: every other pixel sees exactly the first list's Gaussians, so its kept value
    is already the merged render's. With a `claim` counter (CPU), several threads launch the kernel over the
    same `tile_list` and each thread index takes the next unclaimed tile (none left: it returns), so the
    threads share a view's tiles in one launch each, whatever the tiles cost."""
    slot = wp.tid()
    base = slot * _TILE_ACC
    if claim.shape[0] > 0:  # one CPU thread runs this launch's indices in turn: one tile's accumulators
        slot = _claim(claim)
        if slot >= tile_list.shape[0]:
            return
        base = 0
    tile = slot
    if tile_list.shape[0] > 0:
        tile = tile_list[slot]
    vw = views[_view_of(views, tile, 1)]
    local = tile - vw.tile
    x0 = (local % vw.tiles_x) * 16
    y0 = (local / vw.tiles_x) * 16
    x1 = wp.min(x0 + 16, vw.width)
    y1 = wp.min(y0 + 16, vw.height)
    valid = (1 << (x1 - x0)) - 1
    rg = ranges[tile]
    na = rg[0]
    ea = rg[1]
    nb = int(0)  # noqa: UP018 (a Warp dynamic variable)
    eb = int(0)  # noqa: UP018
    # row_done[16 tile + r]: bit j set once pixel (x0 + j, y0 + r) stopped (transmittance < 1e-4); rows
    # whose footprint pixels have all stopped are skipped, and Gaussians whose rows have all stopped
    # (live_rows) without visiting their rows
    for y in range(y0, y1):
        row_done[tile * 16 + y - y0] = 0
    npix = (x1 - x0) * (y1 - y0)
    ndone = int(0)  # noqa: UP018 (a Warp dynamic variable)
    live_rows = (1 << (y1 - y0)) - 1
    kept_row = vec16i()  # per row, the bits of the pixels that keep the first list's image (none: 0)
    if ranges_b.shape[0] > 0:
        nb = ranges_b[tile][0]
        eb = ranges_b[tile][1]
        # the pixels the second list's spans reach (the rows' bits in row_done, inverted below): the rest
        # keep the first list's image and start as stopped
        for k in range(nb, eb):
            rec = record_b[k]
            bb = _bounds(rec, x0, y0, x1, y1)
            for y in range(bb[1], bb[3] + 1):
                sp = _span(rec, y, bb[0], bb[2])
                if sp[0] <= sp[1]:
                    row_done[tile * 16 + y - y0] = row_done[tile * 16 + y - y0] | (
                        ((1 << (sp[1] - x0 + 1)) - 1) ^ ((1 << (sp[0] - x0)) - 1))
        for y in range(y0, y1):
            kept_bits = valid & ~row_done[tile * 16 + y - y0]
            row_done[tile * 16 + y - y0] = kept_bits
            kept_row[y - y0] = kept_bits
            if kept_bits == valid:
                live_rows = live_rows & ~(1 << (y - y0))
    for y in range(y0, y1):
        for x in range(x0, x1):
            if ((kept_row[y - y0] >> (x - x0)) & 1) == 1:
                ndone += 1
        for j in range(16):
            acc[base + (y - y0) * _ROW + j] = 1.0
        for j in range(16, _ROW):
            acc[base + (y - y0) * _ROW + j] = 0.0
    while (na < ea or nb < eb) and ndone < npix:
        rec, na, nb = _merge_next(record, na, ea, record_b, nb, eb)
        bb = _bounds(rec, x0, y0, x1, y1)
        live = bool(False)  # noqa: UP018 (a Warp dynamic variable)
        if bb[1] <= bb[3]:
            live = (live_rows & (((1 << (bb[3] - y0 + 1)) - 1) ^ ((1 << (bb[1] - y0)) - 1))) != 0
        if live:
            box = ((1 << (bb[2] - x0 + 1)) - 1) ^ ((1 << (bb[0] - x0)) - 1)
            # record: centre 0-1, conic 2-4, colour 7-9, depth 10, opacity 11
            res = _composite_rows(acc, base, row_done, tile * 16 - y0, x0, y0, bb[1], bb[3], box, valid,
                                  live_rows, rec[0], rec[1], rec[2], rec[3], rec[4], rec[11], rec[7], rec[8],
                                  rec[9], rec[10], ALPHA_MAX, ALPHA_MIN, T_MIN)
            live_rows = res & 65535
            ndone += res >> 16
    for y in range(y0, y1):
        for x in range(x0, x1):
            if ((kept_row[y - y0] >> (x - x0)) & 1) == 1:
                continue  # the kept image's pixel, final already
            p = vw.pixel + y * vw.width + x
            q = base + (y - y0) * _ROW + x - x0
            t = wp.abs(acc[q])
            a = 1.0 - t
            c = wp.vec3(acc[q + 32], acc[q + 48], acc[q + 64]) + t * vw.background
            out_rgb[p] = wp.vec3(wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0), wp.clamp(c[2], 0.0, 1.0))
            d = acc[q + 16]
            if a > 0.0:
                d = d / a
            out_depth[p] = d
            out_t[p] = a


@wp.func
def _alpha(rec: vec16, px: float, py: float):
    """Record `rec`'s o exp(-d^2 / 2) at the pixel centre (px, py), at most ALPHA_MAX."""
    dx = px - rec[0]
    dy = py - rec[1]
    d2 = rec[2] * dx * dx + 2.0 * rec[3] * dx * dy + rec[4] * dy * dy
    return wp.min(ALPHA_MAX, rec[11] * wp.exp(-0.5 * d2))


@wp.kernel
def _rasterise_pixels(
    ranges: wp.array(dtype=wp.vec2i),
    record: wp.array(dtype=vec16),
    ranges_b: wp.array(dtype=wp.vec2i),
    record_b: wp.array(dtype=vec16),
    views: wp.array(dtype=_View),
    out_rgb: wp.array(dtype=wp.vec3),
    out_depth: wp.array(dtype=wp.float32),
    out_t: wp.array(dtype=wp.float32),
):
    """The CUDA rasteriser: one thread per pixel of the batch (every view's pixels, view after view) walks its
    tile's records front to back with o exp(-d^2/2) evaluated at the pixel (the tile kernel's vectorised exp
    agrees within a few ulp: images within a level of it). With a second list (`ranges_b` not empty) the
    output arrays come holding the first list's own image: the pixels of a tile with no second-list pair keep
    it (their full render composites exactly the first list's Gaussians), every other pixel composites both
    lists merged by depth, the first list's record first on equal depths (with the static Gaussians first: a
    full render's order). Cached and full renders through this kernel are equal bit for bit. (Testing each
    pixel against the second list's ellipses first cost more than it saved: 3.8 against 0.8 ms for push-T's
    front camera on an H100, every record of a tile's list read by every pixel without the early stop.)"""
    p = wp.tid()
    vw = views[_view_of(views, p, 2)]
    local = p - vw.pixel
    y = local / vw.width
    x = local - y * vw.width
    tile = vw.tile + (y / 16) * vw.tiles_x + x / 16
    px = float(x) + 0.5
    py = float(y) + 0.5
    na = ranges[tile][0]
    ea = ranges[tile][1]
    nb = int(0)  # noqa: UP018 (a Warp dynamic variable)
    eb = int(0)  # noqa: UP018
    if ranges_b.shape[0] > 0:
        nb = ranges_b[tile][0]
        eb = ranges_b[tile][1]
        if nb == eb:
            return
    t = float(1.0)  # noqa: UP018 (a Warp dynamic variable)
    rgb = wp.vec3(0.0, 0.0, 0.0)
    dep = float(0.0)  # noqa: UP018
    while na < ea or nb < eb:
        rec, na, nb = _merge_next(record, na, ea, record_b, nb, eb)
        alpha = _alpha(rec, px, py)
        if alpha < ALPHA_MIN:
            continue
        test_t = t * (1.0 - alpha)
        if test_t < T_MIN:
            break
        w = alpha * t
        rgb = rgb + w * wp.vec3(rec[7], rec[8], rec[9])
        dep = dep + w * rec[10]
        t = test_t
    a = 1.0 - t
    c = rgb + t * vw.background
    out_rgb[p] = wp.vec3(wp.clamp(c[0], 0.0, 1.0), wp.clamp(c[1], 0.0, 1.0), wp.clamp(c[2], 0.0, 1.0))
    if a > 0.0:
        dep = dep / a
    out_depth[p] = dep
    out_t[p] = a


def _tile_count(cam: Camera) -> int:
    return ((cam.width + TILE - 1) // TILE) * ((cam.height + TILE - 1) // TILE)


def _use_pixels(device, per_pixel: bool | None) -> bool:
    """Whether to rasterise per pixel (`_rasterise_pixels`): by default on CUDA, per tile on CPU."""
    return not device.is_cpu if per_pixel is None else per_pixel


def _raster_pixels(image, pixels: int, ranges, records, ranges_b, records_b, views) -> None:
    """`_rasterise_pixels` over the first `pixels` pixels of `image` (`ranges_b` empty: a full render)."""
    wp.launch(_rasterise_pixels, dim=pixels, inputs=[ranges, records, ranges_b, records_b, views],
              outputs=[image.rgb, image.depth, image.t], device=image.rgb.device)


def _views(specs: list[tuple], device) -> wp.array:
    """The kernels' views: per (camera, background, first Gaussian, first record, first tile, first pixel) of
    the batch, a _View, written straight into the array's memory (building _View objects and an array of
    them took 4x as long: ~90 us a view)."""
    host = wp.empty(len(specs), dtype=_View, device="cpu")
    # the array's memory as 4-byte words (its .numpy() builds a structured dtype each call: 2x slower)
    words = np.ctypeslib.as_array((ctypes.c_float * (len(specs) * _VIEW_WORDS)).from_address(host.ptr))
    words = words.reshape(len(specs), _VIEW_WORDS)
    ints = words.view(np.int32)
    for row, (cam, background, src, item, tile, pixel) in enumerate(specs):
        w, h = cam.width, cam.height
        w2c = cam.world_to_cam
        tan_x, tan_y = 0.5 * w / cam.fx, 0.5 * h / cam.fy
        lim = (cam.cx / cam.fx + 0.3 * tan_x, (w - cam.cx) / cam.fx + 0.3 * tan_x,
               cam.cy / cam.fy + 0.3 * tan_y, (h - cam.cy) / cam.fy + 0.3 * tan_y)  # fmt: skip
        values = {
            "rot_wc": w2c[:3, :3].ravel(), "t_wc": w2c[:3, 3], "cam_pos": cam.cam_to_world[:3, 3],
            "fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": w, "height": h, "lim": lim,
            "src": src, "item": item, "tile": tile, "tiles_x": (w + TILE - 1) // TILE, "pixel": pixel,
            "background": background,
        }  # fmt: skip
        for name, first, count, is_int in _VIEW_SLOTS:
            (ints if is_int else words)[row, first : first + count] = values[name]
    return host if wp.get_device(device).is_cpu else host.to(device)


def _view_slots() -> tuple[list[tuple[str, int, int, bool]], int]:
    """_View's fields as (name, first 4-byte word, words, integer?), from its memory layout, and its size
    in words."""
    layout = _View.numpy_dtype()
    if layout["itemsize"] % 4:
        raise TypeError("_View: expected a size in 4-byte words")
    slots = []
    for name, fmt, offset in zip(layout["names"], layout["formats"], layout["offsets"], strict=True):
        dt = np.dtype(fmt)
        if dt.base.itemsize != 4 or offset % 4:
            raise TypeError(f"_View.{name}: expected 4-byte fields at 4-byte offsets")
        slots.append((name, offset // 4, int(np.prod(dt.shape)) if dt.shape else 1, dt.base.kind == "i"))
    return slots, layout["itemsize"] // 4


_VIEW_SLOTS, _VIEW_WORDS = _view_slots()


class _Workspace:
    """Per-call, per-Gaussian buffers (allocated per call, so concurrent renders never share them)."""

    def __init__(self, n: int, device) -> None:
        self.record = wp.empty(max(n, 1), dtype=vec16, device=device)
        self.depth = wp.empty(max(n, 1), dtype=wp.float32, device=device)
        self.rect = wp.empty(max(n, 1), dtype=wp.vec4i, device=device)
        self.n_tiles = wp.empty(max(n, 1), dtype=wp.int32, device=device)


class _Image:
    """A view's output buffers: rgb, depth and (after rasterising) alpha, one entry per pixel."""

    def __init__(self, pixels: int, device, like: _Image | None = None) -> None:
        if like is None:
            self.rgb = wp.empty(pixels, dtype=wp.vec3, device=device)
            self.depth = wp.empty(pixels, dtype=wp.float32, device=device)
            self.t = wp.empty(pixels, dtype=wp.float32, device=device)
        else:  # a copy of `like` (a kept static image)
            self.rgb, self.depth, self.t = wp.clone(like.rgb), wp.clone(like.depth), wp.clone(like.t)

    def output(self, h: int, w: int) -> RenderOutput:
        return RenderOutput(rgb=self.rgb.numpy().reshape(h, w, 3), depth=self.depth.numpy().reshape(h, w),
                            alpha=self.t.numpy().reshape(h, w))


class _ChunkBalls:
    """Per chunk of _CHUNK Gaussians of a cloud that stays put: a ball holding their centres (the centre
    of their bounding box, half its diagonal, widened for rounding) and their largest scale magnitude (-1
    where an opacity exceeds 1, which the chunk test does not bound). Clouds in spatial order
    (`GaussianCloud.spatially_sorted`) have small balls, most of them wholly outside a close-up view."""

    def __init__(self, g: DeviceGaussians | None, device=None) -> None:
        device = g.device if g is not None else device
        if g is None or len(g) == 0:  # no chunk bounds: every chunk culled Gaussian by Gaussian
            self.balls = wp.empty(0, dtype=wp.vec4, device=device)
            self.scale = wp.empty(0, dtype=wp.float32, device=device)
            return
        starts = np.arange(0, len(g), _CHUNK)
        means = g.means.numpy().astype(np.float64)
        lo, hi = np.minimum.reduceat(means, starts), np.maximum.reduceat(means, starts)
        radius = 0.5 * np.linalg.norm(hi - lo, axis=1) * (1.0 + 1e-6) + 1e-6
        scale = np.maximum.reduceat(np.abs(g.scales.numpy()).max(axis=1), starts)
        scale = np.where(np.maximum.reduceat(g.opacities.numpy(), starts) <= 1.0, scale, -1.0)
        self.balls = wp.array(np.c_[0.5 * (lo + hi), radius].astype(np.float32), dtype=wp.vec4, device=device)
        self.scale = wp.array(scale.astype(np.float32), dtype=wp.float32, device=device)


@functools.lru_cache(maxsize=8)
def _no_balls(device: str) -> _ChunkBalls:
    return _ChunkBalls(None, device)


def _from_host(a: np.ndarray, dtype, device) -> wp.array:
    """A host array as a kernel argument: on CPU the same memory (the Warp array holds a reference), else
    a device copy."""
    return wp.array(np.ascontiguousarray(a), dtype=dtype, device=device, copy=not device.is_cpu)


def _parts(g) -> list[DeviceGaussians]:
    return [g.static, g.moving] if isinstance(g, SplitGaussians) else [g]


def _project(parts: list[DeviceGaussians], cam: Camera, background, threads: int,
             balls: list[_ChunkBalls | None] | None = None):
    """Stage 1: a record per Gaussian of `parts` (one part after another: their concatenation) as seen by
    `cam` (packed record, depth, tile rectangle, tile count) -> (workspace, the view's kernel array).
    `balls`: per part, its chunks' bounds (CPU; None: cull Gaussian by Gaussian)."""
    device = parts[0].device
    ws = _Workspace(sum(len(p) for p in parts), device)
    views, item = None, 0
    for k, p in enumerate(parts):
        vw = _views([(cam, background, 0, item, 0, 0)], device)
        views = vw if views is None else views
        chunk = _CHUNK if device.is_cpu else 1
        b = balls[k] if balls is not None and chunk == _CHUNK else None
        b = b or _no_balls(str(device))
        pre_in = [p.means, p.quats, p.scales, p.opacities, p.sh, p.sh.shape[1], vw, NEAR, chunk, item,
                  item + len(p), b.balls, b.scale]
        outs = [ws.record, ws.depth, ws.rect, ws.n_tiles]
        split = threads if len(p) >= _SPLIT_PROJECT else 1
        launch_split(_preprocess, (len(p) + chunk - 1) // chunk, pre_in, outs, device, split)
        item += len(p)
    return ws, item, views


_SPLIT_PAIRS = 100_000
_PAIR_CHUNK = 32  # entries (emitting their pairs) or pairs (gathering records) a CPU thread takes in turn
# a part's projection splits over the threads from this many Gaussians: below, handing half to another
# thread (0.1-0.3 ms on a 2-core KVM host) costs more than it saves (push-T's 20,724 moving Gaussians)
_SPLIT_PROJECT = 40_000


class _Bins:
    """Stage 2-3 of a view on the host-sort path: its (tile, record) pairs in (tile, depth, record index)
    order, the records copied into pair order, and each tile's [start, end) in them."""

    def __init__(self, ws: _Workspace, n: int, views, cam: Camera, threads: int) -> None:
        device = ws.record.device
        n_tile_total = _tile_count(cam)
        counts = ws.n_tiles.numpy()[:n]
        visible = np.flatnonzero(counts).astype(np.int32)
        # by depth, equal depths in the records' order (the radix sorts' order too): the visible depths are
        # > 0, so their float bits sort as integers; with the rank below them every key is distinct
        keys64 = ws.depth.numpy()[visible].view(np.uint32).astype(np.uint64) << np.uint64(32)
        keys64 |= np.arange(len(visible), dtype=np.uint64)
        keys64.sort()
        order = visible[(keys64 & np.uint64(0xFFFFFFFF)).astype(np.intp)]
        offsets = np.cumsum(counts[order], dtype=np.int64)
        total = int(offsets[-1]) if len(offsets) else 0
        if total >= 2**31:
            raise ValueError(f"render: {total} Gaussian-tile pairs exceed int32; downsample the cloud")
        keys = wp.empty(max(total, 1), dtype=wp.int32, device=device)
        values = wp.empty(max(total, 1), dtype=wp.int32, device=device)
        emit_in = [
            _from_host(order, wp.int32, device),
            _from_host(offsets.astype(np.int32), wp.int32, device),
            ws.rect, ws.n_tiles, views,
        ]  # fmt: skip
        # a thread per part only where the pairs are many (below ~1e5 two threads cost more than one)
        split = threads if total >= _SPLIT_PAIRS else 1
        chunk = _PAIR_CHUNK if device.is_cpu else 1
        chunks = (len(order) + chunk - 1) // chunk
        launch_split(_emit_pairs, chunks, emit_in + [chunk], [keys, values], device, split)
        tile_of_pair = keys.numpy()[:total].astype(np.uint16 if n_tile_total < 65536 else np.int32)
        perm = np.argsort(tile_of_pair, kind="stable")
        sorted_values = _from_host(values.numpy()[:total][perm], wp.int32, device)
        bounds = np.searchsorted(tile_of_pair[perm], np.arange(n_tile_total + 1))
        self.ranges_np = np.stack([bounds[:-1], bounds[1:]], axis=1).astype(np.int32)
        self.ranges = _from_host(self.ranges_np, wp.vec2i, device)
        # records copied into pair order, so the rasteriser streams them instead of chasing random ids
        self.records = wp.empty(max(total, 1), dtype=vec16, device=device)
        launch_split(_gather_records, (total + chunk - 1) // chunk, [sorted_values, ws.record, chunk, total],
                     [self.records], device, split)


def _raster(tiles: np.ndarray, first: _Bins, second: _Bins | None, views, cam: Camera, image: _Image,
            threads: int, board: WorkBoard | None = None) -> None:
    """Stage 4: rasterise the given tiles of one view into `image`, merging `second`'s lists into
    `first`'s by depth. On CPU with threads, each thread launches the kernel over all the tiles and takes
    the next unclaimed one in turn (load balance at tile grain, a launch per thread); with a `board`,
    threads done with their own views launch it too."""
    device = image.rgb.device
    shared = board is not None and device.is_cpu
    parts = (board.owners if shared else threads) if device.is_cpu else 1
    tile_list = _from_host(tiles.astype(np.int32), wp.int32, device)
    claim = wp.zeros(1 if parts > 1 else 0, dtype=wp.int32, device=device)
    if second is None:
        b_ranges, b_records = wp.empty(0, dtype=wp.vec2i, device=device), first.records
    else:
        b_ranges, b_records = second.ranges, second.records
    inputs = [tile_list, claim, first.ranges, first.records, b_ranges, b_records, views]
    row_done = wp.empty(_tile_count(cam) * 16, dtype=wp.int32, device=device)
    outputs = [image.rgb, image.depth, image.t, row_done]
    acc = (1 if parts > 1 else len(tiles)) * _TILE_ACC  # claiming: one thread, a tile at a time, a launch

    def task() -> None:
        wp.launch(_rasterise, dim=len(tiles), inputs=inputs,
                  outputs=outputs + [wp.empty(acc, dtype=wp.float32, device=device)], device=device)

    if shared and parts > 1:
        board.share([task] * parts)
    else:
        run_threads([task] * parts)


def _render_warp_one(
    g: DeviceGaussians | SplitGaussians, cam: Camera, background: np.ndarray, threads: int,
    host_sort: bool | None = None, board: WorkBoard | None = None, static_balls: _ChunkBalls | None = None,
) -> RenderOutput:
    """One camera, every Gaussian. host_sort (default: on CPU) sorts the pairs with NumPy, else it is a
    batch of one view (Warp's radix sorts: the CUDA path; the tests also run it on CPU). `board`: see
    `_raster`. `static_balls`: the chunk bounds of a SplitGaussians' static part (RenderCache.balls)."""
    parts = _parts(g)
    device = parts[0].device
    if not (device.is_cpu if host_sort is None else host_sort):
        return _render_warp_batch([(_whole(g), cam)], background)[0]
    if device.is_cpu and threads > 1:
        wp.load_module(device=device)  # compile once, not concurrently in the worker threads
    ws, n, views = _project(parts, cam, background, threads, [static_balls, None])
    bins = _Bins(ws, n, views, cam, threads)
    image = _Image(cam.width * cam.height, device)
    _raster(np.arange(_tile_count(cam)), bins, None, views, cam, image, threads, board)
    return image.output(cam.height, cam.width)


class _Kept:
    """What a RenderCache keeps of one (static cloud, camera, background): the static Gaussians' pairs
    in (tile, depth) order and the image they make alone."""

    def __init__(self, static: DeviceGaussians, cam: Camera, background, threads: int,
                 per_pixel: bool | None = None) -> None:
        self.static = static  # holds the arrays (and so their addresses, part of the key) alive
        device = static.device
        if device.is_cpu and threads > 1:
            wp.load_module(device=device)  # compile once, not concurrently in the worker threads
        ws, n, views = _project([static], cam, background, threads)
        self.bins = _Bins(ws, n, views, cam, threads)
        self.image = _Image(cam.width * cam.height, device)
        if _use_pixels(device, per_pixel):  # the kernel of the device's renders
            _raster_pixels(self.image, cam.width * cam.height, self.bins.ranges, self.bins.records,
                           wp.empty(0, dtype=wp.vec2i, device=device), self.bins.records, views)
        else:
            _raster(np.arange(_tile_count(cam)), self.bins, None, views, cam, self.image, threads)


def _render_kept(kept: _Kept, moving: DeviceGaussians, cam: Camera, background, threads: int,
                 board: WorkBoard | None = None) -> RenderOutput:
    """A view of [static | moving] from the kept static work: only the moving Gaussians are projected and
    binned; the tiles they reach are rasterised with their lists merged into the kept ones by depth, every
    other tile is the kept static image. Equals `_render_warp_one` of the whole cloud, bit for bit.
    `board`: see `_raster`."""
    image = _Image(0, moving.device, like=kept.image)
    if len(moving):
        if moving.device.is_cpu and threads > 1:
            wp.load_module(device=moving.device)
        ws, n, views = _project([moving], cam, background, threads)
        bins = _Bins(ws, n, views, cam, threads)
        dirty = np.flatnonzero(bins.ranges_np[:, 1] > bins.ranges_np[:, 0])
        if len(dirty):
            _raster(dirty, kept.bins, bins, views, cam, image, threads, board)
    return image.output(cam.height, cam.width)


class RenderCache:
    """Per-camera work on the static Gaussians kept between renders (the "warp" backend, CPU and CUDA;
    it pays on CPU: on CUDA a full render costs about the same, see the module's docstring).

    Pass it to `render_batch(..., cache=)` with views whose cloud is a `SplitGaussians(static, moving)`.
    For each (static cloud, camera pose and intrinsics, background) asked for a second time it keeps the
    static Gaussians' records, their (tile, depth)-ordered pair lists and the image they make alone, on
    the render's device; that render and later ones of that camera project only the moving Gaussians (see
    `_render_kept`). A camera that moves (a new key every render) never builds an entry: it gets full
    renders, whose projection culls the static Gaussians 32 at a time where a ball around them misses the
    view (`balls`: kept per static cloud; a cloud in spatial order, `GaussianCloud.spatially_sorted`, has
    small balls). Images equal full renders bit for bit. The static cloud is known by its arrays' addresses: a
    different cloud makes new entries, but after writing into a kept static cloud's arrays call `clear()`.
    Entries (at most `max_entries`, least recently used dropped) may be shared by many worlds' views."""

    def __init__(self, max_entries: int = 16) -> None:
        self.max_entries = int(max_entries)
        self._kept: OrderedDict[tuple, _Kept] = OrderedDict()
        self._seen: OrderedDict[tuple, None] = OrderedDict()
        self._balls: OrderedDict[tuple, _ChunkBalls] = OrderedDict()
        self._lock = threading.Lock()  # renders from several threads may share a cache
        self.builds = self.hits = self.misses = 0  # counters, for tests and benchmarks

    def clear(self) -> None:
        with self._lock:
            self._kept.clear()
            self._seen.clear()
            self._balls.clear()

    def balls(self, static: DeviceGaussians) -> _ChunkBalls:
        """The static cloud's chunk bounds, for the full renders of moving cameras (computed once)."""
        key = self._arrays(static)
        with self._lock:
            out = self._balls.get(key)
            if out is None:
                out = self._balls[key] = _ChunkBalls(static)
                while len(self._balls) > self.max_entries:
                    self._balls.popitem(last=False)
            return out

    @staticmethod
    def _arrays(static: DeviceGaussians) -> tuple:
        return str(static.device), tuple((a.ptr, a.shape) for a in (static.means, static.quats, static.scales,
                                                                     static.opacities, static.sh))

    @staticmethod
    def _key(static: DeviceGaussians, cam: Camera, background) -> tuple:
        arrays = RenderCache._arrays(static)
        intr = np.array([cam.fx, cam.fy, cam.cx, cam.cy, cam.width, cam.height], np.float64)
        pose = np.asarray(cam.cam_to_world, np.float64)
        bg = np.asarray(background, np.float32)
        return arrays, intr.tobytes(), pose.tobytes(), bg.tobytes()

    def lookup(self, static: DeviceGaussians, cam: Camera, background, threads: int) -> _Kept | None:
        """The kept work for this view, built on the second request of its key; None: render in full."""
        key = self._key(static, cam, background)
        with self._lock:
            return self._lookup(key, static, cam, background, threads)

    def _lookup(self, key: tuple, static: DeviceGaussians, cam: Camera, background, threads: int):
        kept = self._kept.get(key)
        if kept is not None:
            self._kept.move_to_end(key)
            self.hits += 1
            return kept
        if key not in self._seen:
            self._seen[key] = None
            while len(self._seen) > 4096:  # keys of moving cameras
                self._seen.popitem(last=False)
            self.misses += 1
            return None
        del self._seen[key]
        kept = self._kept[key] = _Kept(static, cam, background, threads)
        while len(self._kept) > self.max_entries:
            self._kept.popitem(last=False)
        self.builds += 1
        return kept


class _Batch:
    """Stages 1-3 of a batch of views, every stage once for all of them (the CUDA path; it runs on CPU
    too): the views' clouds in one buffer, a record per (view, Gaussian), one depth sort, pairs keyed by
    the batch's tile ids (view after view), one stable tile sort -> each tile's [start, end) in `ranges`
    and the records in pair order. `views` holds each view's first tile and pixel in the batch's images."""

    def __init__(self, jobs: list[tuple[DeviceGaussians, Camera]], background) -> None:
        device = self.device = jobs[0][0].device
        starts: dict[int, int] = {}
        clouds: list[DeviceGaussians] = []
        for g, _ in jobs:
            if id(g) not in starts:
                starts[id(g)] = sum(len(c) for c in clouds)
                clouds.append(g)
        parents = [g.parent() for g in clouds]
        if len(clouds) > 1 and len({id(root) for root, _ in parents}) == 1:
            cloud = parents[0][0]  # segments of one cloud (e.g. a twin's worlds): read it in place
            starts = {id(g): first for g, (_, first) in zip(clouds, parents, strict=True)}
        else:
            cloud = clouds[0] if len(clouds) == 1 else DeviceGaussians.concatenate(clouds)
        views, self.shapes = [], []
        item = tile = pixel = 0
        for g, cam in jobs:
            views.append((cam, background, starts[id(g)], item, tile, pixel))
            self.shapes.append((pixel, cam.height, cam.width))
            item, tile, pixel = item + len(g), tile + _tile_count(cam), pixel + cam.width * cam.height
        self.tiles, self.pixels = tile, pixel
        vw = self.views = _views(views, device)
        n = item
        ws = _Workspace(n, device)
        g = cloud
        chunk = _CHUNK if device.is_cpu else 1
        none = _no_balls(str(device))
        inputs = [g.means, g.quats, g.scales, g.opacities, g.sh, g.sh.shape[1], vw, NEAR, chunk, 0, n,
                  none.balls, none.scale, 0]
        wp.launch(_preprocess, dim=(n + chunk - 1) // chunk, inputs=inputs,
                  outputs=[ws.record, ws.depth, ws.rect, ws.n_tiles], device=device)
        total = 0
        if n:  # (no Gaussians, e.g. a cached view with nothing moving: no sorts)
            dkeys = wp.empty(2 * n, dtype=wp.float32, device=device)
            order = wp.empty(2 * n, dtype=wp.int32, device=device)
            wp.launch(_init_depth_sort, dim=n, inputs=[ws.depth], outputs=[dkeys, order], device=device)
            wp.utils.radix_sort_pairs(dkeys, order, n)
            counts = wp.empty(n, dtype=wp.int32, device=device)
            wp.launch(_gather_counts, dim=n, inputs=[order, ws.n_tiles], outputs=[counts], device=device)
            offsets = wp.empty(n, dtype=wp.int32, device=device)
            wp.utils.array_scan(counts, offsets, inclusive=True)
            total = int(offsets.numpy()[-1])  # the one device -> host wait before the images
        if total < 0:  # the int32 scan overflowed
            raise ValueError("render: the views' Gaussian-tile pairs exceed int32; render fewer views a call")
        keys = wp.empty(max(2 * total, 2), dtype=wp.int32, device=device)
        values = wp.empty(max(2 * total, 2), dtype=wp.int32, device=device)
        self.ranges = wp.zeros(tile, dtype=wp.vec2i, device=device)
        self.records = wp.empty(max(total, 1), dtype=vec16, device=device)
        if total:
            wp.launch(_emit_pairs, dim=n, inputs=[order, offsets, ws.rect, ws.n_tiles, vw, 1, 0],
                      outputs=[keys, values], device=device)
            wp.utils.radix_sort_pairs(keys, values, total)
            wp.launch(_tile_ranges, dim=total, inputs=[keys, total], outputs=[self.ranges], device=device)
            wp.launch(_gather_records, dim=total, inputs=[values, ws.record, 1, total, 0],
                      outputs=[self.records], device=device)

    def raster(self, image: _Image, ranges, records, per_pixel: bool) -> list[RenderOutput]:
        """Rasterise every tile of the batch into `image`: the batch's own lists (a full render), or, with
        `ranges`, `records` (the kept static lists, indexed by the batch's tile ids), those merged with
        the batch's (image: the kept images); per pixel (the CUDA kernel) or per tile (the CPU one)."""
        device = self.device
        if ranges is None:
            ranges, records, ranges_b = self.ranges, self.records, wp.empty(0, dtype=wp.vec2i, device=device)
        else:
            ranges_b = self.ranges
        if per_pixel:
            _raster_pixels(image, self.pixels, ranges, records, ranges_b, self.records, self.views)
        else:
            row_done = wp.empty(self.tiles * 16, dtype=wp.int32, device=device)
            wp.launch(_rasterise, dim=self.tiles,
                      inputs=[wp.empty(0, dtype=wp.int32, device=device), wp.empty(0, dtype=wp.int32,
                              device=device), ranges, records, ranges_b, self.records, self.views],
                      outputs=[image.rgb, image.depth, image.t, row_done,
                               wp.empty(self.tiles * _TILE_ACC, dtype=wp.float32, device=device)],
                      device=device)  # fmt: skip
        rgb, depth, alpha = image.rgb.numpy(), image.depth.numpy(), image.t.numpy()
        return [
            RenderOutput(rgb=rgb[p : p + h * w].reshape(h, w, 3), depth=depth[p : p + h * w].reshape(h, w),
                         alpha=alpha[p : p + h * w].reshape(h, w))
            for p, h, w in self.shapes
        ]  # fmt: skip


def _render_warp_batch(jobs: list[tuple[DeviceGaussians, Camera]], background,
                       per_pixel: bool | None = None) -> list[RenderOutput]:
    """Every view of `jobs` in one launch per stage (render_batch's path on CUDA; it runs on CPU too).
    per_pixel (default: on CUDA) rasterises with one thread per pixel, else per tile: then each image
    equals the view rendered alone with the same (radix) sorts, bit for bit."""
    batch = _Batch(jobs, background)
    return batch.raster(_Image(batch.pixels, batch.device), None, None, _use_pixels(batch.device, per_pixel))


def _render_kept_batch(items: list[tuple[_Kept, DeviceGaussians, Camera]], background,
                       per_pixel: bool | None = None) -> list[RenderOutput]:
    """Views of [static | moving] from kept static work, one launch per stage for all of them (the CUDA
    path of cached views; it runs on CPU too): the moving clouds batched as in `_render_warp_batch`, every
    tile of the batch rasterised with its lists merged into the view's kept ones (a tile no moving pair
    reaches keeps its kept pixels at once). Equals `_render_warp_batch` of the whole clouds with the same
    kernel, bit for bit."""
    batch = _Batch([(moving, cam) for _, moving, cam in items], background)
    device = batch.device
    first: dict[int, int] = {}  # id(kept) -> its first record in `records`
    distinct: list[_Kept] = []
    for kept, _, _ in items:
        if id(kept) not in first:
            first[id(kept)] = sum(len(k.bins.records) for k in distinct)
            distinct.append(kept)
    if len(distinct) == 1:
        records = distinct[0].bins.records  # e.g. one camera of many worlds: its kept lists read in place
    else:
        records = wp.empty(sum(len(k.bins.records) for k in distinct), dtype=vec16, device=device)
        for k in distinct:
            wp.copy(records, k.bins.records, first[id(k)], 0, len(k.bins.records))
    ranges = wp.array(np.concatenate([k.bins.ranges_np + first[id(k)] for k, _, _ in items]), dtype=wp.vec2i,
                      device=device)  # fmt: skip
    image = _Image(batch.pixels, device)
    for (kept, _, _), (p, h, w) in zip(items, batch.shapes, strict=True):
        for name in ("rgb", "depth", "t"):
            wp.copy(getattr(image, name), getattr(kept.image, name), p, 0, h * w)
    return batch.raster(image, ranges, records, _use_pixels(device, per_pixel))


def _whole(g: DeviceGaussians | SplitGaussians) -> DeviceGaussians:
    return g.merged() if isinstance(g, SplitGaussians) else g


def render_views(views: list[tuple[GaussianCloud | DeviceGaussians | SplitGaussians, Camera]],
                 background: np.ndarray, device: str, threads: int,
                 cache: RenderCache | None = None) -> list[RenderOutput]:
    """The "warp" backend (see render.render_batch): host clouds uploaded once each; with a `cache`, the
    views of a SplitGaussians whose camera has not moved reuse the kept static work (RenderCache). On CUDA
    the full views run every stage once for all of them (`_render_warp_batch`), and the cached ones
    likewise (`_render_kept_batch`); on CPU, with at least as many views as threads, the views are dealt to
    the threads (each thread renders whole views, every stage in parallel; the full renders first, then the
    cached ones, each thread taking the next view when done), else each view in turn is split over the
    threads by Gaussians and tiles."""
    uploaded: dict[int, DeviceGaussians | SplitGaussians] = {}
    jobs: list[tuple[DeviceGaussians | SplitGaussians, Camera]] = []
    for cloud, cam in views:
        g = uploaded.get(id(cloud))
        if g is None:
            keep = isinstance(cloud, DeviceGaussians | SplitGaussians)
            g = uploaded[id(cloud)] = cloud if keep else cloud.to_device(device)
            if str(g.device) != str(wp.get_device(device)):
                raise ValueError(f"render: DeviceGaussians live on {g.device}, but device={device!r}")
        jobs.append((g, cam))
    kept = [
        cache.lookup(g.static, cam, background, threads)
        if cache is not None and isinstance(g, SplitGaussians) else None
        for g, cam in jobs
    ]  # fmt: skip
    outs: list = [None] * len(jobs)
    balls = {
        id(g): cache.balls(g.static)
        for (g, _), k in zip(jobs, kept, strict=True)
        if k is None and cache is not None and isinstance(g, SplitGaussians) and g.device.is_cpu
    }  # fmt: skip

    def one(i: int, th: int, board: WorkBoard | None = None) -> None:
        g, cam = jobs[i]
        if kept[i] is None:
            outs[i] = _render_warp_one(g, cam, background, th, board=board, static_balls=balls.get(id(g)))
        else:
            outs[i] = _render_kept(kept[i], g.moving, cam, background, th, board=board)

    full = [i for i in range(len(jobs)) if kept[i] is None]
    if not jobs[0][0].device.is_cpu:  # one launch per stage for the full views, one for the cached ones
        cached = [i for i in range(len(jobs)) if kept[i] is not None]
        if full:
            for i, out in zip(full, _render_warp_batch([(_whole(jobs[i][0]), jobs[i][1]) for i in full],
                                                       background), strict=True):  # fmt: skip
                outs[i] = out
        if cached:
            items = [(kept[i], jobs[i][0].moving, jobs[i][1]) for i in cached]
            for i, out in zip(cached, _render_kept_batch(items, background), strict=True):
                outs[i] = out
        return outs
    if threads > 1 and len(jobs) >= threads:
        # as many views as threads: whole views per thread (every stage runs in parallel, not only kernels;
        # one world's moving camera beside its cached one: 11.9 against 13.3 ms split view by view)
        wp.load_module(device=jobs[0][0].device)
        order = full + [i for i in range(len(jobs)) if kept[i] is not None]
        taken = iter(range(len(order)))
        lock = threading.Lock()
        workers = min(threads, len(jobs))
        # a thread out of views helps rasterise the others' (one world: the wrist's full render beside
        # the front's cached one) by launching their tile kernel too (the tiles are claimed one at a
        # time); only the last views share their tiles, the others rasterise on their own thread
        board = WorkBoard(workers)

        def work():
            try:
                while True:
                    with lock:
                        k = next(taken, None)
                    if k is None:
                        break
                    one(order[k], 1, board if k >= len(order) - workers else None)
            finally:
                board.finish()
            board.help()

        run_threads([work] * workers)
    else:
        for i in range(len(jobs)):
            one(i, threads)
    return outs
