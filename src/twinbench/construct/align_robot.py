"""Register a robot scan to its URDF and label every Gaussian with its link (DESIGN §1 step 3).

Pipeline (numpy + scipy's KD-tree, no Open3D):

1. Sample the URDF link meshes posed at the known configuration q (about 2,000 points per link, with
   the faces' normals), in the world = robot-base frame.
2. Drop scan floaters (points with few neighbours: statistical density filter), and, when the scale is
   unknown, pre-scale the scan by the ratio of RMS radii.
3. Global registration: voxel down-sampling, FPFH features (Rusu et al. 2009) on k-nearest neighbours,
   nearest-feature correspondences, RANSAC over 3-point samples (edge-length consistency check,
   Umeyama fit, correspondence inlier count), the best hypotheses re-scored on the whole cloud.
4. Refinement: trimmed point-to-plane ICP (rigid or similarity) against the dense URDF samples.
5. Labels: each Gaussian takes the link of its nearest URDF sample (fingers included); its distance to
   that sample is kept so floaters can be dropped.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from twinbench.robot.model import RobotModel
from twinbench.transforms import matrix_to_rotvec, rotvec_to_matrix, transform_points

# ------------------------------------------------------------------------------------------------
# URDF samples


@dataclass
class RobotSamples:
    """Points on the posed link meshes: world positions, unit normals, link index per point."""

    points: np.ndarray  # (N, 3)
    normals: np.ndarray  # (N, 3)
    link_index: np.ndarray  # (N,) int64 index into model.link_names
    links: list[str]  # model.link_names


def sample_robot_surface(
    model: RobotModel,
    q: np.ndarray | None = None,
    *,
    points_per_link: int = 2000,
    meshes: str = "visual",
    seed: int = 0,
) -> RobotSamples:
    """Sample `points_per_link` points on every link mesh posed by FK at `q` (default: home)."""
    if meshes not in ("visual", "collision"):
        raise ValueError(f"meshes: expected 'visual' or 'collision', got {meshes!r}")
    if points_per_link < 1:
        raise ValueError(f"points_per_link: must be >= 1, got {points_per_link}")
    table = model.visual_meshes if meshes == "visual" else model.collision_meshes
    if not table:
        table = model.collision_meshes or model.visual_meshes
    if not table:
        raise ValueError(f"robot {model.name!r} has no link meshes (was it loaded with load_meshes=False?)")
    q = model.home_q if q is None else model.check_q(q)
    poses = model.fk(q)
    rng = np.random.default_rng(seed)
    pts, nrm, idx = [], [], []
    for name in model.link_names:
        mesh: trimesh.Trimesh | None = table.get(name)
        if mesh is None or len(mesh.faces) == 0:
            continue
        p, faces = trimesh.sample.sample_surface(mesh, int(points_per_link), seed=rng)
        li = model.link_index(name)
        pose = poses[li]
        pts.append(transform_points(pose, p))
        nrm.append(np.asarray(mesh.face_normals)[faces] @ pose[:3, :3].T)
        idx.append(np.full(len(p), li, dtype=np.int64))
    return RobotSamples(np.concatenate(pts), np.concatenate(nrm), np.concatenate(idx), list(model.link_names))


# ------------------------------------------------------------------------------------------------
# point-cloud helpers


def density_filter(points: np.ndarray, radius: float, min_fraction: float = 0.1) -> np.ndarray:
    """Boolean mask of points with at least `min_fraction` x the median neighbour count within `radius`
    (drops isolated floaters; surfaces keep their points)."""
    tree = cKDTree(points)
    counts = tree.query_ball_point(points, radius, return_length=True)
    return counts >= max(2.0, min_fraction * float(np.median(counts)))


def voxel_downsample(points: np.ndarray, voxel: float) -> np.ndarray:
    """Mean point of every occupied voxel of size `voxel` (sorted by voxel key)."""
    keys = np.floor(points / voxel).astype(np.int64)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    out = np.zeros((len(counts), 3))
    np.add.at(out, inv, points)
    return out / counts[:, None]


def estimate_normals(points: np.ndarray, k: int = 16, tree: cKDTree | None = None) -> np.ndarray:
    """Unit normals by PCA over the k nearest neighbours (smallest-eigenvalue direction, sign arbitrary)."""
    tree = cKDTree(points) if tree is None else tree
    k = min(k, len(points))
    _, nn = tree.query(points, k=k)
    nb = points[nn] - points[nn].mean(axis=1, keepdims=True)
    cov = np.einsum("nki,nkj->nij", nb, nb)
    _, vecs = np.linalg.eigh(cov)
    return vecs[:, :, 0]


def fpfh_features(points: np.ndarray, normals: np.ndarray, k: int = 32, bins: int = 11) -> np.ndarray:
    """Fast Point Feature Histograms (3 x `bins` values) over each point's k nearest neighbours.

    Pair features (alpha, phi, theta) in the Darboux frame of the source point, the pair ordered so that
    the source normal makes the smaller angle with the connecting line (normal signs do not matter
    up to that choice); SPFH per point, then FPFH = SPFH + mean over neighbours of SPFH / distance,
    each block normalised to sum 100.
    """
    n = len(points)
    k = min(k + 1, n)
    tree = cKDTree(points)
    dist, nn = tree.query(points, k=k)
    dist, nn = dist[:, 1:], nn[:, 1:]
    ps = np.broadcast_to(points[:, None, :], nn.shape + (3,))
    ns = np.broadcast_to(normals[:, None, :], nn.shape + (3,))
    pt, nt = points[nn], normals[nn]
    d = pt - ps
    dn = np.linalg.norm(d, axis=-1, keepdims=True)
    d = d / np.maximum(dn, 1e-12)
    a1 = np.abs(np.einsum("nki,nki->nk", ns, d))
    a2 = np.abs(np.einsum("nki,nki->nk", nt, d))
    swap = (a1 < a2)[..., None]  # use the normal with the smaller angle to the line as u
    u = np.where(swap, nt, ns)
    other = np.where(swap, ns, nt)
    dd = np.where(swap, -d, d)
    # orient u along the line (sign-free normals): u . d >= 0
    sgn = np.sign(np.einsum("nki,nki->nk", u, dd))[..., None]
    u = u * np.where(sgn == 0, 1.0, sgn)
    other = other * np.sign(np.einsum("nki,nki->nk", other, u) + 1e-12)[..., None]
    v = np.cross(u, dd)
    v /= np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)
    w = np.cross(u, v)
    alpha = np.einsum("nki,nki->nk", v, other)
    phi = np.einsum("nki,nki->nk", u, dd)
    theta = np.arctan2(np.einsum("nki,nki->nk", w, other), np.einsum("nki,nki->nk", u, other))

    def hist(x, lo, hi):
        b = np.clip(((x - lo) / (hi - lo) * bins).astype(np.int64), 0, bins - 1)
        h = np.zeros((n, bins))
        np.add.at(h, (np.repeat(np.arange(n), b.shape[1]), b.reshape(-1)), 1.0)
        return h * (100.0 / b.shape[1])

    spfh = np.concatenate([hist(alpha, -1, 1), hist(phi, -1, 1), hist(theta, -np.pi, np.pi)], axis=1)
    wgt = 1.0 / np.maximum(dist, 1e-12)
    agg = np.einsum("nk,nkf->nf", wgt, spfh[nn])
    for blk in range(3):
        s = agg[:, blk * bins : (blk + 1) * bins]
        s *= 100.0 / np.maximum(s.sum(axis=1, keepdims=True), 1e-12)
    return spfh + agg


# ------------------------------------------------------------------------------------------------
# similarity fits


def fit_similarity(src: np.ndarray, dst: np.ndarray, *, with_scale: bool = True, weights=None) -> np.ndarray:
    """Least-squares similarity (Umeyama) 4x4 mapping src -> dst; batched over leading axes of (..., n, 3).
    Without scale it is the Kabsch rigid fit (reflections fixed)."""
    src = np.asarray(src, dtype=np.float64)
    dst = np.asarray(dst, dtype=np.float64)
    w = np.ones(src.shape[:-1]) if weights is None else np.asarray(weights, dtype=np.float64)
    w = w / w.sum(axis=-1, keepdims=True)
    ms = np.einsum("...n,...ni->...i", w, src)
    md = np.einsum("...n,...ni->...i", w, dst)
    a = src - ms[..., None, :]
    b = dst - md[..., None, :]
    cov = np.einsum("...n,...ni,...nj->...ij", w, b, a)
    u, sv, vt = np.linalg.svd(cov)
    det = np.linalg.det(u) * np.linalg.det(vt)
    dg = np.ones(cov.shape[:-1])
    dg[..., 2] = np.where(det < 0, -1.0, 1.0)
    rot = np.einsum("...ij,...j,...jk->...ik", u, dg, vt)
    if with_scale:
        var = np.einsum("...n,...ni,...ni->...", w, a, a)
        s = np.einsum("...i,...i->...", sv, dg) / np.maximum(var, 1e-300)
    else:
        s = np.ones(cov.shape[:-2])
    out = np.zeros(cov.shape[:-2] + (4, 4))
    out[..., :3, :3] = rot * s[..., None, None]
    out[..., :3, 3] = md - np.einsum("...ij,...j->...i", out[..., :3, :3], ms)
    out[..., 3, 3] = 1.0
    return out


def similarity_scale(t: np.ndarray) -> float:
    """Uniform scale of a 4x4 similarity."""
    return float(np.cbrt(np.linalg.det(np.asarray(t)[:3, :3])))


def _apply(t: np.ndarray, p: np.ndarray) -> np.ndarray:
    return p @ t[:3, :3].T + t[:3, 3]


# ------------------------------------------------------------------------------------------------
# global registration


def ransac_registration(
    src: np.ndarray,
    dst: np.ndarray,
    src_feat: np.ndarray,
    dst_feat: np.ndarray,
    *,
    inlier_dist: float,
    with_scale: bool,
    scale_range: tuple[float, float] = (0.67, 1.5),
    iterations: int = 60000,
    batch: int = 4000,
    edge_tolerance: float = 0.1,
    top: int = 20,
    seed: int = 0,
) -> tuple[np.ndarray, float]:
    """Feature-matched RANSAC: returns (4x4 src -> dst transform, fitness of it on the whole cloud)."""
    rng = np.random.default_rng(seed)
    ftree = cKDTree(dst_feat)
    _, match = ftree.query(src_feat, k=1)
    # mutual matches are more reliable; fall back to all when there are too few
    _, back = cKDTree(src_feat).query(dst_feat, k=1)
    mutual = back[match] == np.arange(len(src))
    ci = np.flatnonzero(mutual) if mutual.sum() >= 30 else np.arange(len(src))
    cs, cd = src[ci], dst[match[ci]]
    m = len(ci)
    if m < 3:
        raise ValueError("registration: fewer than 3 feature correspondences; is the scan empty?")
    cand_t, cand_score = [], []
    for start in range(0, iterations, batch):
        nb = min(batch, iterations - start)
        sel = rng.integers(0, m, size=(nb, 3))
        ps, pd = cs[sel], cd[sel]
        es = np.linalg.norm(ps - np.roll(ps, 1, axis=1), axis=-1)
        ed = np.linalg.norm(pd - np.roll(pd, 1, axis=1), axis=-1)
        ratio = ed / np.maximum(es, 1e-12)
        ok = np.all(es > 3 * inlier_dist, axis=1)
        if with_scale:
            r0 = ratio.mean(axis=1)
            ok &= np.all(np.abs(ratio / r0[:, None] - 1.0) < edge_tolerance, axis=1)
            ok &= (r0 > scale_range[0]) & (r0 < scale_range[1])
        else:
            ok &= np.all(np.abs(ratio - 1.0) < edge_tolerance, axis=1)
        if not ok.any():
            continue
        t = fit_similarity(ps[ok], pd[ok], with_scale=with_scale)
        moved = np.einsum("bij,nj->bni", t[:, :3, :3], cs) + t[:, None, :3, 3]
        score = (np.linalg.norm(moved - cd[None], axis=-1) < inlier_dist).sum(axis=1)
        keep = np.argsort(-score)[:top]
        cand_t.append(t[keep])
        cand_score.append(score[keep])
    if not cand_t:
        raise ValueError("registration: RANSAC found no consistent 3-point sample; check the scan and q")
    cand_t = np.concatenate(cand_t)
    cand_score = np.concatenate(cand_score)
    best = np.argsort(-cand_score)[:top]
    tree = cKDTree(dst)
    fits = []
    for t in cand_t[best]:
        d, _ = tree.query(_apply(t, src), k=1, distance_upper_bound=inlier_dist)
        fits.append(np.isfinite(d).mean())
    i = int(np.argmax(fits))
    return cand_t[best][i], float(fits[i])


# ------------------------------------------------------------------------------------------------
# ICP


def icp_point_to_plane(
    src: np.ndarray,
    dst: np.ndarray,
    dst_normals: np.ndarray,
    init: np.ndarray,
    *,
    max_dist: float,
    min_dist: float = 0.003,
    with_scale: bool = False,
    iterations: int = 60,
    tol: float = 1e-7,
    tree: cKDTree | None = None,
) -> tuple[np.ndarray, float, float]:
    """Trimmed point-to-plane ICP from `init`. The correspondence distance starts at `max_dist` and
    shrinks to 3 robust sigmas of the residuals (not below `min_dist`). Returns (transform, fitness,
    inlier RMSE): fitness = fraction of src points matched within the final distance."""
    tree = cKDTree(dst) if tree is None else tree
    t = np.array(init, dtype=np.float64)
    thr = float(max_dist)
    for _ in range(iterations):
        p = _apply(t, src)
        d, j = tree.query(p, k=1, distance_upper_bound=thr)
        ok = np.isfinite(d)
        if ok.sum() < 10:
            break
        pp, qq, nn = p[ok], dst[j[ok]], dst_normals[j[ok]]
        c = pp.mean(axis=0)
        pc = pp - c
        r = np.einsum("ni,ni->n", nn, pp - qq)
        cols = [np.cross(pc, nn), nn]
        if with_scale:
            cols.append(np.einsum("ni,ni->n", nn, pc)[:, None])
        a = np.concatenate(cols, axis=1)
        # Geman-McClure-like robust weights on the plane residuals
        sig = max(1.4826 * float(np.median(np.abs(r))), 1e-4)
        wgt = 1.0 / (1.0 + (r / (2.0 * sig)) ** 2)
        x, *_ = np.linalg.lstsq(a * wgt[:, None], -r * wgt, rcond=None)
        omega, dt = x[:3], x[3:6]
        ds = x[6] if with_scale else 0.0
        ang = np.linalg.norm(omega)
        inc = np.eye(4)
        inc[:3, :3] = (1.0 + ds) * rotvec_to_matrix(omega)
        inc[:3, 3] = c + dt - inc[:3, :3] @ c
        t = inc @ t
        new_thr = max(min_dist, min(thr, 3.0 * 1.4826 * float(np.median(d[ok]))))
        step = ang + np.linalg.norm(dt) + abs(ds)
        if step < tol and new_thr >= thr * 0.999:
            break
        thr = new_thr
    d, _ = tree.query(_apply(t, src), k=1, distance_upper_bound=thr)
    ok = np.isfinite(d)
    rmse = float(np.sqrt(np.mean(d[ok] ** 2))) if ok.any() else float("inf")
    return t, float(ok.mean()), rmse


# ------------------------------------------------------------------------------------------------
# the whole registration


@dataclass
class RegistrationResult:
    """Scan -> world transform (similarity when scale was estimated), quality and labels."""

    transform: np.ndarray  # (4, 4) scan frame -> world (robot base) frame
    scale: float
    fitness: float  # fraction of (filtered) scan points within the final ICP distance of the URDF samples
    rmse: float  # inlier RMSE (m)
    global_fitness: float  # RANSAC hypothesis fitness, before ICP
    labels: np.ndarray  # (N,) int64 link index per scan Gaussian
    distances: np.ndarray  # (N,) distance to the nearest URDF sample after alignment (m)
    links: list[str]
    timings: dict[str, float] = field(default_factory=dict)

    def report(self, max_distance: float) -> dict:
        """JSON-ready summary: transform, scale, fitness, RMSE and per-link counts."""
        near = self.distances <= max_distance
        counts = np.bincount(self.labels[near], minlength=len(self.links))
        return {
            "transform": self.transform.tolist(),
            "scale": self.scale,
            "rotation_deg": float(np.degrees(np.linalg.norm(matrix_to_rotvec(self.transform[:3, :3]
                                                                             / self.scale)))),
            "fitness": self.fitness,
            "rmse_m": self.rmse,
            "global_fitness": self.global_fitness,
            "gaussians": int(len(self.labels)),
            "labelled": int(near.sum()),
            "dropped_far": int((~near).sum()),
            "max_distance_m": float(max_distance),
            "per_link": {name: int(c) for name, c in zip(self.links, counts, strict=True) if c > 0},
            "timings_s": self.timings,
        }


@dataclass(frozen=True)
class RegistrationParams:
    """Knobs of `register_robot` (defaults suit a ~1 m arm scanned at mm resolution)."""

    points_per_link: int = 2000  # URDF samples per link for registration
    label_points_per_link: int = 20000  # denser samples for the nearest-sample labels
    voxel: float = 0.012  # global-registration voxel (m)
    feature_k: int = 32  # neighbours of the FPFH features
    estimate_scale: bool = False
    # with estimate_scale: the accepted scan -> world scale, relative to the first estimate from the clouds'
    # spreads (so a scan in any unit, e.g. COLMAP's, registers; the fit may refine that estimate this much)
    scale_range: tuple[float, float] = (0.5, 2.0)
    ransac_iterations: int = 60000
    icp_max_dist: float = 0.03
    icp_points: int = 40000  # scan points used by ICP (random subset when more)
    floater_radius: float = 0.02  # density filter radius (m, scan units)
    seed: int = 0


def register_robot(
    scan_points: np.ndarray,
    model: RobotModel,
    q: np.ndarray | None = None,
    params: RegistrationParams = RegistrationParams(),
    *,
    scan_normals: np.ndarray | None = None,
    init: np.ndarray | None = None,
) -> RegistrationResult:
    """Register robot scan points (its Gaussians' means, scan frame) to the URDF posed at `q`, then
    label them (`label_points`; `scan_normals` (N, 3), NaN rows allowed, e.g. `gaussian_normals`).

    `init` (4x4 scan -> world) skips the global stage when the scan is already roughly aligned.
    """
    import time

    pts = np.asarray(scan_points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 10:
        raise ValueError(f"scan points must have shape (N >= 10, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError("scan points contain NaN or inf")
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    reg = sample_robot_surface(model, q, points_per_link=params.points_per_link, seed=params.seed)
    lab = sample_robot_surface(model, q, points_per_link=params.label_points_per_link, seed=params.seed + 1)
    dst, dst_n = lab.points, lab.normals
    tree = cKDTree(dst)
    timings["urdf_samples"] = time.perf_counter() - t0

    def rms_radius(p: np.ndarray) -> float:
        return float(np.sqrt(np.mean(np.sum((p - p.mean(axis=0)) ** 2, axis=1))))

    urdf_radius = rms_radius(reg.points)

    def spread_ratio(p: np.ndarray) -> float:  # the URDF samples' RMS radius over the points'
        return urdf_radius / max(rms_radius(p), 1e-12)

    t0 = time.perf_counter()
    # the floater radius is in metres: in scan units when the scan's unit is estimated
    keep = density_filter(pts, params.floater_radius / (spread_ratio(pts) if params.estimate_scale else 1.0))
    clean = pts[keep]
    timings["density_filter"] = time.perf_counter() - t0

    rng = np.random.default_rng(params.seed)
    global_fit = float("nan")
    s0 = spread_ratio(clean) if params.estimate_scale else 1.0  # first estimate of scan -> world scale
    if init is None:
        t0 = time.perf_counter()
        cs_, cd_ = clean.mean(axis=0), reg.points.mean(axis=0)
        pre = np.eye(4)
        pre[:3, :3] *= s0
        pre[:3, 3] = cd_ - s0 * cs_
        src_v = voxel_downsample(_apply(pre, clean), params.voxel)
        dst_v = voxel_downsample(reg.points, params.voxel)
        src_f = fpfh_features(src_v, estimate_normals(src_v), k=params.feature_k)
        dst_f = fpfh_features(dst_v, estimate_normals(dst_v), k=params.feature_k)
        lo, hi = params.scale_range
        t_g, global_fit = ransac_registration(
            src_v, dst_v, src_f, dst_f,
            inlier_dist=1.5 * params.voxel,
            with_scale=params.estimate_scale,
            scale_range=(lo, hi) if params.estimate_scale else (1.0, 1.0),
            iterations=params.ransac_iterations,
            seed=params.seed,
        )
        init = t_g @ pre
        timings["global"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    sub = clean
    if len(clean) > params.icp_points:
        sub = clean[rng.choice(len(clean), params.icp_points, replace=False)]
    t, fitness, rmse = icp_point_to_plane(
        sub, dst, dst_n, init, max_dist=params.icp_max_dist, with_scale=params.estimate_scale, tree=tree
    )
    timings["icp"] = time.perf_counter() - t0
    scale = similarity_scale(t)
    lo, hi = params.scale_range
    if params.estimate_scale and not lo * s0 <= scale <= hi * s0:
        raise ValueError(
            f"registration: estimated scale {scale:.4g} is outside {params.scale_range} x {s0:.4g} (the "
            "first estimate, from the spread of the scan's robot Gaussians against the URDF's): the "
            "registration failed; check that segment's robot box holds the robot and little else, --urdf "
            "and --q"
        )
    t0 = time.perf_counter()
    world_n = None if scan_normals is None else np.asarray(scan_normals, dtype=np.float64) @ t[:3, :3].T
    labels, d = label_points(_apply(t, pts), lab, normals=world_n, tree=tree)
    timings["labels"] = time.perf_counter() - t0
    return RegistrationResult(
        transform=t, scale=scale, fitness=fitness, rmse=rmse, global_fitness=global_fit,
        labels=labels, distances=d, links=lab.links, timings=timings,
    )


def gaussian_normals(cloud, flatness: float = 0.5) -> np.ndarray:
    """Unit normals of flat Gaussians (the axis of the smallest scale), NaN rows for Gaussians whose
    smallest scale is not below `flatness` x the middle one (no usable orientation)."""
    from twinbench.transforms import quat_to_matrix

    rot = quat_to_matrix(cloud.quats)
    s = np.sort(cloud.log_scales.astype(np.float64), axis=1)
    axis = np.argmin(cloud.log_scales, axis=1)
    n = rot[np.arange(len(cloud)), :, axis]
    n[(s[:, 0] - s[:, 1]) > np.log(flatness)] = np.nan
    return n


def label_points(
    points: np.ndarray,
    samples: RobotSamples,
    *,
    normals: np.ndarray | None = None,
    sigma: float | None = None,
    normal_weight: float = 30.0,
    k: int = 32,
    tree: cKDTree | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Link label and distance of each world point: its nearest URDF sample, or, where a unit normal is
    given (finite row), the sample among the k nearest minimising (d / sigma)^2 + w (1 - |n . n_s|),
    which separates links meeting at an angle. `sigma` (the scan noise) defaults to a robust estimate:
    1.4826 x the median distance of the points to their nearest sample's tangent plane (>= 0.5 mm).
    Returns (labels int64, distance to the chosen sample)."""
    tree = cKDTree(samples.points) if tree is None else tree
    d, j = tree.query(points, k=1)
    labels = samples.link_index[j].copy()
    if normals is None:
        return labels, d
    if sigma is None:
        plane = np.abs(np.einsum("ni,ni->n", samples.normals[j], points - samples.points[j]))
        sigma = max(1.4826 * float(np.median(plane)), 5e-4)
    ok = np.all(np.isfinite(normals), axis=1)
    if ok.any():
        dk, jk = tree.query(points[ok], k=min(k, len(samples.points)))
        cos = np.abs(np.einsum("nki,ni->nk", samples.normals[jk], normals[ok]))
        best = np.argmin((dk / sigma) ** 2 + normal_weight * (1.0 - cos), axis=1)
        rows = np.arange(len(best))
        labels[ok] = samples.link_index[jk[rows, best]]
        d[ok] = dk[rows, best]
    return labels, d


# ------------------------------------------------------------------------------------------------
# files: the align-robot output folder


def align_robot_files(robot_path, out, *, urdf: str = "builtin:xarm7_gripper", q=None,
                      params: RegistrationParams = RegistrationParams(), max_distance: float = 0.02,
                      also=(), min_inliers: float = 0.5) -> dict:
    """`twinbench align-robot`: register the robot's Gaussians (a 3DGS file) to the URDF at `q` (default:
    the robot's home), write the output folder (`write_aligned_robot`) and return the report. Refused (no
    files written) when under `min_inliers` of the Gaussians end within `max_distance` of the links."""
    from twinbench.gaussians.io import load_gaussians
    from twinbench.twin.build import load_spec_robot
    from twinbench.twin.spec import RobotSpec

    for name, value in (("max_distance", max_distance), ("voxel", params.voxel),
                        ("icp_max_dist", params.icp_max_dist), ("floater_radius", params.floater_radius)):
        if not (isinstance(value, int | float) and math.isfinite(value) and 0 < value <= 10):
            raise ValueError(f"--{name.replace('_', '-')}: expected a length in (0, 10] m, got {value!r}")
    model = load_spec_robot(RobotSpec(urdf=urdf))
    q = model.home_q if q is None else model.check_q(np.asarray(q, dtype=np.float64))
    cloud = load_gaussians(robot_path)
    extent = float(np.ptp(cloud.means, axis=0).max()) if len(cloud.means) else 0.0
    # (with --scale the scan's unit is unknown: its extent says nothing)
    if len(np.unique(cloud.means, axis=0)) < 10 or (extent < 4 * params.voxel and not params.estimate_scale):
        raise ValueError(f"{robot_path}: the robot's {len(cloud.means)} Gaussians span {extent:.4g} m "
                         f"(fewer than 10 distinct points, or under 4 voxels of {params.voxel} m): not a "
                         "scan of a robot to register; check the file (segment's robot.ply) or --voxel")
    if not 0.0 <= min_inliers <= 1.0:
        raise ValueError(f"--min-inliers: expected a fraction in [0, 1], got {min_inliers!r}")
    res = register_robot(cloud.means, model, q, params, scan_normals=gaussian_normals(cloud))
    near = float(np.mean(res.distances <= max_distance))
    if not np.any(res.distances <= max_distance) or near < min_inliers:
        hint = "" if params.estimate_scale else "if the scan is not in metres (e.g. COLMAP's), add --scale; "
        raise ValueError(f"{robot_path}: after registration {100 * near:.1f} % of the robot's Gaussians lie "
                         f"within --max-distance {max_distance} m of the URDF's links (--min-inliers "
                         f"{min_inliers}; nearest {float(res.distances.min()):.3g} m): the registration "
                         f"failed; {hint}check --urdf, --q (the scan's joint configuration) and that "
                         "segment's robot box holds the robot and little else (or lower --min-inliers)")
    write_aligned_robot(out, cloud, res, q, urdf, max_distance, also)
    return res.report(max_distance)


def write_aligned_robot(out, cloud, res: RegistrationResult, q, urdf: str, max_distance: float,
                        also=()) -> None:
    """robot.ply + labels.npz (labels int32 into `links`) + far.ply + report.json (+ aligned copies)."""
    from twinbench.construct._json import write_json
    from twinbench.gaussians.io import load_gaussians, save_gaussians

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    moved = cloud.transform(res.transform)
    near = res.distances <= max_distance
    save_gaussians(moved.subset(near), out / "robot.ply")
    save_gaussians(moved.subset(~near), out / "far.ply")
    np.savez(out / "labels.npz", labels=res.labels[near].astype(np.int32), links=np.asarray(res.links))
    rep = res.report(max_distance)
    rep.update({"urdf": urdf, "q": np.asarray(q).tolist(), "links": list(res.links)})
    aligned = {}
    for path in also:
        p = Path(path)
        dst = out / "aligned" / p.name
        dst.parent.mkdir(exist_ok=True)
        save_gaussians(load_gaussians(p).transform(res.transform), dst)
        aligned[str(p)] = f"aligned/{p.name}"
    rep["aligned"] = aligned
    write_json(out / "report.json", rep)


def read_aligned_robot(folder) -> tuple:
    """(cloud, labels, links, q, urdf) of an align-robot output folder."""
    import json

    from twinbench.gaussians.io import load_gaussians

    folder = Path(folder)
    rep = json.loads((folder / "report.json").read_text())
    with np.load(folder / "labels.npz", allow_pickle=False) as z:
        labels, links = z["labels"], [str(s) for s in z["links"]]
    return load_gaussians(folder / "robot.ply"), labels, links, rep["q"], rep["urdf"]
