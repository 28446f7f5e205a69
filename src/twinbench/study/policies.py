"""Perception-based controllers: the task's scripted expert driven by object poses estimated from the camera
image instead of the privileged state (policy kind `perceive`, spec `[NAME=]perceive:CONFIG.json`).

Push-T: each perception step segments the T in the front camera image with a colour model (a Gaussian in
RGB per image region, the goal overlay's pixels apart; `calibrate_colors` fits it on labelled images of
the real workcell, so a twin whose colours are off perceives worse), keeps the largest blob, then fits the
T's pose (x, y, theta) so that the projection of its solid (the twin's outline, extruded) lies inside the
blob in the image: starts at the blob's centroid on the table with 12 headings, the best 3 refined by
Nelder-Mead on the mean signed pixel distance of the projected points to the blob's edge. The camera is
the calibrated one in the config (else the env's). The expert then acts on [estimate, goal, estimated
msd]. Levels: `noise_m` / `noise_rad` (Gaussian noise on every estimate), `latency` (the estimate of
`latency` perception steps ago), `gain` (the fraction of the expert's step towards its target that is
commanded), `period` (perceive every `period` steps).

Rope routing: the rope expert plans once, from [marked end, the rope point 4 cm from it, centroid, clip
pose]; `RopeEstimator` gives the rope's part from the front image (a colour model of the rope's body and of
its marked end, fitted as push-T's on labelled real images; the blob's pixels back-projected onto the
table), the clip's pose is the twin's; `PerceptionRope` adds the level's noise and gain (`LEVELS`).

Toy packing: the toy expert plans once, from [toy pose, box pose]; `ToyEstimator` segments the toy's torso
and the box by colour (classes fitted on labelled real images) and fits each one's planar pose from its
blob (`PlanarPoseFit`: the torso's surface, the box's mesh; projected inside and covering the blob);
`PerceptionToy` adds the level's noise and gain.
"""

from __future__ import annotations

import json
from collections import deque
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from twinbench.errors import InputError

CHI2_3_999 = 16.27  # chi-square, 3 degrees of freedom, 99.9 %: a pixel within this of the T's colour is T
COLOR_TOLERANCE = 8.0  # 0-255 levels (a std) added to the calibrated colour spread: the drift a detector
# tuned on a few images must tolerate (the spread of those images is mostly sensor noise, ~3 levels)
TRACK_COST_PX = -1.0  # a tracked fit worse than this (mean signed pixel distance) restarts the search


@dataclass(frozen=True)
class PerceptionConfig:
    """Everything a perception controller knows besides the twin's rules (goal, outline, tool radius)."""

    colors: dict  # {"plain" | "overlay": {"mean": [3], "cov": [[3x3]]}} (0-255 RGB), see calibrate_colors
    camera: str = "front"
    threshold: float = CHI2_3_999  # squared Mahalanobis distance to the T's colour
    camera_model: dict | None = None  # {fx, fy, cx, cy, width, height, cam_to_world}; None: the env's
    noise_m: float = 0.0
    noise_rad: float = 0.0
    latency: int = 0
    gain: float = 1.0
    period: int = 1
    min_pixels: int = 20  # fewer T pixels: nothing seen (the policy keeps its last estimate)
    extra: dict = field(default_factory=dict)  # free labels (e.g. the level's name)

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict, where: str = "perception config") -> PerceptionConfig:
        known = set(cls.__dataclass_fields__)
        unknown = sorted(set(d) - known)
        if unknown or "colors" not in d:
            raise InputError(f"{where}: fields must be among {sorted(known)} with 'colors' required "
                             f"(write it with twinbench.study.policies.write_config); unknown: {unknown}")
        cfg = cls(**d)
        if not (cfg.gain > 0 and cfg.period >= 1 and min(cfg.latency, cfg.noise_m, cfg.noise_rad) >= 0):
            raise InputError(f"{where}: gain must be > 0, period >= 1, latency, noise_m, noise_rad >= 0")
        return cfg


def write_config(cfg: PerceptionConfig, path: str | Path) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(cfg.to_dict(), indent=1))
    return path


def read_config(path: str | Path) -> PerceptionConfig:
    path = Path(path)
    try:
        d = json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(f"perception config {path} does not exist; give perceive:PATH to a JSON file "
                         "written by twinbench.study.policies.write_config") from None
    except json.JSONDecodeError as err:
        raise InputError(f"perception config {path}: not JSON ({err})") from None
    if not isinstance(d, dict):
        raise InputError(f"perception config {path}: expected a JSON object")
    return PerceptionConfig.from_dict(d, str(path))


# ---- geometry -------------------------------------------------------------------------------------------
def camera_dict(cam) -> dict:
    """A `gaussians.camera.Camera` as the config's plain `camera_model`."""
    return {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy, "width": cam.width, "height": cam.height,
            "cam_to_world": np.asarray(cam.cam_to_world).tolist()}


def _camera(model: dict):
    from twinbench.gaussians.camera import Camera

    return Camera(**{**model, "cam_to_world": np.asarray(model["cam_to_world"], np.float64)})


def _solid_points(outline, spacing: float = 0.006) -> np.ndarray:
    """Points on the surface of the outline's prism (top face and walls), block frame: their projection is
    the block's silhouette."""
    lo, hi = outline.bounds()
    gx, gy = np.meshgrid(np.arange(lo[0], hi[0] + 1e-9, spacing), np.arange(lo[1], hi[1] + 1e-9, spacing))
    flat = np.c_[gx.ravel(), gy.ravel()]
    flat = flat[outline.contains(flat, tol=1e-6)]
    poly = outline.polygon
    edges = []
    for a, b in zip(poly, np.roll(poly, -1, axis=0), strict=True):
        k = max(int(np.linalg.norm(b - a) / spacing), 1)
        edges.append(a + (np.arange(k) / k)[:, None] * (b - a))
    edges = np.concatenate(edges)
    zs = np.linspace(0.0, outline.height, max(int(round(outline.height / spacing)), 1) + 1)
    return np.concatenate([np.c_[flat, np.full(len(flat), outline.height)],
                           *[np.c_[edges, np.full(len(edges), z)] for z in zs[:-1]]])


def _rays(cam, uv: np.ndarray, z: float) -> tuple[np.ndarray, np.ndarray]:
    """World directions (N, 3) of pixels `uv` (N, 2; pixel centres at +0.5) with depth 1, and the ray
    parameter t (N,) where each meets the plane at height z (t <= 0: it does not, in front of the camera)."""
    c2w = cam.cam_to_world
    rays = np.c_[(uv[:, 0] - cam.cx) / cam.fx, (uv[:, 1] - cam.cy) / cam.fy, np.ones(len(uv))] @ c2w[:3, :3].T
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (z - c2w[2, 3]) / rays[:, 2]
    return rays, np.nan_to_num(t, nan=-1.0, posinf=-1.0, neginf=-1.0)


def table_points(cam, uv: np.ndarray, z: float) -> np.ndarray:
    """Back-projection of pixels `uv` onto the plane at height z (world xy)."""
    rays, t = _rays(cam, uv, z)
    return (cam.cam_to_world[:3, 3] + t[:, None] * rays)[:, :2]


def pixel_areas(cam, uv: np.ndarray, z: float) -> np.ndarray:
    """The area (m^2) each pixel `uv` covers on the plane at height z: weights that undo perspective."""
    rays, t = _rays(cam, uv, z)
    norm = np.linalg.norm(rays, axis=1)
    return t**2 * norm**3 / (cam.fx * cam.fy * np.maximum(np.abs(rays[:, 2]), 1e-9))


def project(cam, world: np.ndarray) -> np.ndarray:
    """Pixel (u, v) of world points (N, 3) in camera `cam`."""
    w2c = cam.world_to_cam
    p = world @ w2c[:3, :3].T + w2c[:3, 3]
    z = np.maximum(p[:, 2], 1e-6)
    return np.c_[cam.fx * p[:, 0] / z + cam.cx, cam.fy * p[:, 1] / z + cam.cy]


def _planar(x: float, y: float, th: float) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, x], [s, c, y]])


def color_models(colors: dict) -> dict:
    """{region: (mean, inverse covariance)} of a config's `colors` ({region: {"mean", "cov"}})."""
    out = {}
    for region, m in colors.items():
        cov = np.asarray(m["cov"], np.float64) + np.eye(3) * 1e-3
        out[region] = (np.asarray(m["mean"], np.float64), np.linalg.inv(cov))
    return out


def _mahalanobis2(pixels: np.ndarray, model) -> np.ndarray:
    mean, icov = model
    d = np.asarray(pixels, np.float64) - mean
    return np.einsum("ni,ij,nj->n", d, icov, d)


def near_color(pixels: np.ndarray, model, threshold: float) -> np.ndarray:
    """(N,) bool: pixels (N, 3) within squared Mahalanobis distance `threshold` of `model` (mean, inv cov)."""
    return _mahalanobis2(pixels, model) < threshold


def pixel_centres(cam) -> np.ndarray:
    """(H * W, 2) the (u, v) centres of every pixel of `cam`, row after row."""
    jj, ii = np.meshgrid(np.arange(cam.width), np.arange(cam.height))
    return np.c_[jj.ravel() + 0.5, ii.ravel() + 0.5]


def table_mask(cam, height: float, workspace) -> np.ndarray:
    """(H, W) bool: pixels whose ray meets the plane at `height` inside `workspace` ((x0, y0), (x1, y1))."""
    uv = pixel_centres(cam)
    xy = table_points(cam, uv, height)
    lo, hi = np.asarray(workspace, np.float64)
    inside = (_rays(cam, uv, height)[1] > 0) & np.all((xy >= lo) & (xy <= hi), axis=1)
    return inside.reshape(cam.height, cam.width)


class PlanarPoseFit:
    """Fits the planar pose (x, y, theta) of a rigid shape resting on the table from its blob in one camera's
    image: `points` (N, 3) sample the shape in its own frame (z up from its base), and the fit places them
    so that their projection lies inside the blob. With `coverage`, the projection must also cover the
    blob (a shape whose turned or shifted projection fits inside its blob, e.g. a box seen from above its
    walls, is otherwise ambiguous)."""

    def __init__(self, points, camera, coverage: bool = False):
        self.points, self.cam, self.coverage = np.asarray(points, np.float64), camera, bool(coverage)

    def project(self, pose_xyth) -> np.ndarray:
        """Pixel (u, v) of the shape's points at planar pose (x, y, theta), (N, 2)."""
        m = _planar(*pose_xyth)
        xy = self.points[:, :2] @ m[:, :2].T + m[:, 2]
        return project(self.cam, np.c_[xy, self.points[:, 2]])

    def fit(self, mask: np.ndarray, previous=None) -> np.ndarray:
        """(x, y, theta) of the shape whose blob is `mask` (H, W bool, not empty). `previous`: a recent
        estimate to start from (else 12 headings about the blob's centre, the best 3 refined by Nelder-Mead).
        The fit minimises the mean signed distance (pixels, negative inside) of the projected points to the
        blob's edge; with `coverage`, the mean distance of the points outside the blob to it plus the mean
        distance of (up to 500 of) the blob's pixels to the nearest projected point."""
        from scipy import ndimage
        from scipy.optimize import minimize
        from scipy.spatial import cKDTree

        sdf = ndimage.distance_transform_edt(~mask) - ndimage.distance_transform_edt(mask)
        h, w = mask.shape
        if self.coverage:  # up to 500 of the blob's pixels (u, v), pixel centres at integer coordinates
            blob = np.argwhere(mask)[:, ::-1].astype(np.float64)
            blob = blob[:: max(len(blob) // 500, 1)]

        def cost(p):
            uv = self.project(p) - 0.5  # pixel centres at integer coordinates
            d = ndimage.map_coordinates(sdf, [np.clip(uv[:, 1], 0, h - 1), np.clip(uv[:, 0], 0, w - 1)],
                                        order=1, mode="nearest")
            if not self.coverage:
                return float(np.mean(np.minimum(d, 20.0)))
            gap = np.minimum(cKDTree(uv).query(blob)[0], 20.0)
            return float(np.mean(np.clip(d, 0.0, 20.0)) + np.mean(gap))

        def refine(start, step):
            simplex = np.array([start, start + [step, 0, 0], start + [0, step, 0], start + [0, 0, 20 * step]])
            res = minimize(cost, start, method="Nelder-Mead", options={
                "initial_simplex": simplex, "xatol": 2e-4, "fatol": 1e-3, "maxfev": 200})
            x = np.asarray(res.x, np.float64)
            x[2] = (x[2] + np.pi) % (2 * np.pi) - np.pi
            return x, float(res.fun)

        if previous is not None:  # tracking: refine the last estimate; a poor fit falls back to the search
            x, c = refine(np.asarray(previous, np.float64), 0.004)
            if c < TRACK_COST_PX:
                return x
        ii, jj = np.nonzero(mask)
        lo, hi = self.points[:, 2].min(), self.points[:, 2].max()
        centre = table_points(self.cam, np.c_[jj + 0.5, ii + 0.5], 0.5 * (lo + hi)).mean(0)
        starts = [np.r_[centre, th] for th in np.linspace(-np.pi, np.pi, 12, endpoint=False)]
        costs = [cost(s) for s in starts]
        fits = [refine(starts[k], 0.01) for k in np.argsort(costs)[:3]]  # the 3 best headings, refined
        return min(fits, key=lambda f: f[1])[0]


class TPoseEstimator(PlanarPoseFit):
    """Segments a block of footprint `outline` by colour in one camera's images and fits its planar pose."""

    def __init__(self, outline, camera, colors: dict, threshold: float = CHI2_3_999,
                 overlay: np.ndarray | None = None, min_pixels: int = 20):
        super().__init__(_solid_points(outline), camera)
        self.outline = outline
        self.threshold, self.min_pixels = float(threshold), int(min_pixels)
        self.overlay = None if overlay is None else np.asarray(overlay, bool)
        self.models = color_models(colors)

    # -- segmentation
    def segment(self, image: np.ndarray) -> np.ndarray:
        """(H, W) bool: pixels of the block's colour (largest connected blob after a 3x3 opening)."""
        from scipy import ndimage

        img = np.asarray(image, np.float64)
        mask = np.zeros(img.shape[:2], bool)
        regions = {"plain": ~self.overlay if self.overlay is not None else np.ones_like(mask)}
        if self.overlay is not None:
            regions["overlay"] = self.overlay
        for region, where in regions.items():
            model = self.models.get(region, self.models["plain"])
            mask[where] = near_color(img[where], model, self.threshold)
        return largest_blob(ndimage.binary_opening(mask, np.ones((3, 3), bool)))

    def estimate(self, image: np.ndarray, previous=None) -> np.ndarray | None:
        """(x, y, theta) of the block (`PlanarPoseFit.fit`), or None when fewer than `min_pixels` of its
        colour are seen."""
        mask = self.segment(image)
        if mask.sum() < self.min_pixels:
            return None
        return self.fit(mask, previous)


def largest_blob(mask: np.ndarray, connectivity: int = 1) -> np.ndarray:
    """The largest connected blob of `mask` (4-connected; 8-connected with `connectivity` 2)."""
    from scipy import ndimage

    labels, n = ndimage.label(mask, ndimage.generate_binary_structure(2, connectivity))
    if n == 0:
        return mask
    return labels == (1 + int(np.argmax(np.bincount(labels.ravel())[1:])))


def class_masks(image: np.ndarray, models: dict, threshold: float) -> dict[str, np.ndarray]:
    """{class: (H, W) bool} for each colour class of `models` but "table": pixels within squared Mahalanobis
    distance `threshold` of the class's colour and more likely under it than under the table's (when the
    models have a "table": pixels where an object meets the table are mixed)."""
    img = np.asarray(image, np.float64)
    shape, flat = img.shape[:2], img.reshape(-1, 3)
    d2 = {k: _mahalanobis2(flat, m) for k, m in models.items()}
    loglik = {k: -0.5 * (d2[k] - np.linalg.slogdet(m[1])[1]) for k, m in models.items()}  # Gaussian, + c
    table = loglik.get("table", np.full(len(flat), -np.inf))
    return {k: ((d2[k] < threshold) & (loglik[k] > table)).reshape(shape) for k in models if k != "table"}


ALONG_M = 0.04  # the rope point the expert orients its grasp by: 4 cm from the marked end (rope_routing)


class RopeEstimator:
    """Segments the rope by colour (its body and its marked end, `colors` {"rope", "mark"}) in one camera's
    images and estimates what the rope expert plans from, on the table: its marked end, the rope point
    ALONG_M from it, and its centroid. Pixels count only where their ray meets the plane at the rope's
    height (`height`) inside `workspace` ((x0, y0), (x1, y1)); the rope is the 8-connected blob of rope or
    mark colour with the most mark pixels. Its pixels are back-projected onto that plane (weighted by the
    area each covers there: perspective undone); the marked end is the rope point farthest from the
    centroid within 5 cm of the mark pixels' centre."""

    def __init__(self, camera, colors: dict, threshold: float = CHI2_3_999, min_pixels: int = 20,
                 height: float = 0.005, workspace=((0.2, -0.4), (0.8, 0.4))):
        self.cam, self.threshold, self.min_pixels = camera, float(threshold), int(min_pixels)
        self.height = float(height)
        self.models = color_models(colors)
        uv = pixel_centres(camera)
        self._table = table_mask(camera, height, workspace)
        self._xy, self._area = table_points(camera, uv, height), pixel_areas(camera, uv, height)

    def segment(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rope, mark) (H, W) bool masks: the rope's blob and its marked-end pixels. A pixel is the rope's
        or the mark's when that colour is within `threshold` and more likely than the table's (the colour
        model's "table", when it has one: the pixels where the rope meets the table are mixed)."""
        from scipy import ndimage

        seen = class_masks(image, self.models, self.threshold)
        mark, rope = seen["mark"] & self._table, seen["rope"] & self._table
        labels, n = ndimage.label(rope | mark, np.ones((3, 3), bool))
        if n == 0:
            return rope | mark, mark
        sizes = np.bincount(labels.ravel(), minlength=n + 1)
        marks = np.bincount(labels[mark], minlength=n + 1)
        best = max(range(1, n + 1), key=lambda k: (marks[k], sizes[k]))
        blob = labels == best
        return blob, mark & blob

    def estimate(self, image: np.ndarray) -> np.ndarray | None:
        """[marked end (3), the rope point ALONG_M from it (3), centroid (3)] (world, at `height`), or None
        when fewer than `min_pixels` rope pixels (or no mark pixel) are seen."""
        rope, mark = self.segment(image)
        if rope.sum() < self.min_pixels or not mark.any():
            return None
        idx, m = np.flatnonzero(rope.ravel()), np.flatnonzero(mark.ravel())
        pts, w = self._xy[idx], self._area[idx]
        centroid = (pts * w[:, None]).sum(0) / w.sum()
        mark_xy = (self._xy[m] * self._area[m, None]).sum(0) / self._area[m].sum()
        near = np.linalg.norm(pts - mark_xy, axis=1) <= 0.05
        cand = pts[near] if near.any() else pts
        end = cand[np.argmax(np.linalg.norm(cand - centroid, axis=1))]
        d = np.linalg.norm(pts - end, axis=1)
        ring = np.abs(d - ALONG_M) <= 0.006
        if ring.any():
            along = (pts[ring] * w[ring, None]).sum(0) / w[ring].sum()
        else:  # a short blob: towards the centroid
            along = end + ALONG_M * (centroid - end) / max(np.linalg.norm(centroid - end), 1e-9)
        z = self.height
        return np.r_[end, z, along, z, centroid, z]


TORSO_HALF_M = 0.03  # the toy's torso (the part between its limbs) is within this of its frame's x axis


def toy_shapes(u, box_points: int = 800) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(torso, torso points, box points) of env `u`'s twin: which of the toy's particles are its torso (the
    part between the limbs, which the expert grasps: within TORSO_HALF_M of the toy frame's x axis), the
    torso's surface (its Gaussians' centres, toy frame), and points sampled on the box collider's mesh (box
    frame)."""
    import trimesh

    name = u.rules.roles["toy"]
    torso = np.abs(u.twin.rest_particles(name)[:, 1]) <= TORSO_HALF_M
    skin = np.asarray(next(o for o in u.twin.spec.objects if o.name == name).gaussians.means, np.float64)
    box = next(c for c in u.twin.spec.colliders if c.name == u.rules.roles["box"])
    mesh = trimesh.Trimesh(np.asarray(box.vertices), np.asarray(box.faces), process=False)
    pts, _ = trimesh.sample.sample_surface(mesh, box_points, seed=0)
    return torso, skin[np.abs(skin[:, 1]) <= TORSO_HALF_M], np.asarray(pts, np.float64)


class ToyEstimator:
    """Segments the toy's torso (colour "toy") and the box ("box") in one camera's images and fits each
    one's planar pose (`PlanarPoseFit` with the torso's surface and the box's mesh points). A pixel counts
    for an object only where its ray meets the table, or the plane of the object's top, inside `workspace`
    ((x0, y0), (x1, y1)); each object is the largest blob of its colour after a 3x3 opening."""

    def __init__(self, camera, colors: dict, torso_points, box_points, threshold: float = CHI2_3_999,
                 min_pixels: int = 20, workspace=((0.2, -0.4), (0.8, 0.4))):
        self.toy = PlanarPoseFit(torso_points, camera, coverage=True)
        self.box = PlanarPoseFit(box_points, camera, coverage=True)
        self.models, self.threshold, self.min_pixels = color_models(colors), float(threshold), int(min_pixels)
        table = table_mask(camera, 0.0, workspace)
        self._where = {k: table | table_mask(camera, float(fit.points[:, 2].max()), workspace)
                       for k, fit in (("toy", self.toy), ("box", self.box))}

    def segment(self, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(torso, box) (H, W) bool masks (`class_masks`, then each colour's largest blob)."""
        from scipy import ndimage

        seen = class_masks(image, self.models, self.threshold)
        return tuple(largest_blob(ndimage.binary_opening(seen[k] & self._where[k], np.ones((3, 3), bool)))
                     for k in ("toy", "box"))

    def estimate(self, image: np.ndarray) -> np.ndarray | None:
        """[toy x, y, theta, box x, y, theta] (the toy frame's and the box frame's planar poses), or None
        when fewer than `min_pixels` of either colour are seen."""
        toy, box = self.segment(image)
        if min(toy.sum(), box.sum()) < self.min_pixels:
            return None
        return np.r_[self.toy.fit(toy), self.box.fit(box)]


# ---- colour calibration -----------------------------------------------------------------------------------
def points_mask(cam, uv: np.ndarray) -> np.ndarray:
    """(H, W) bool: the pixels of `cam` that points at pixel coordinates `uv` (N, 2) fall in."""
    h, w = cam.height, cam.width
    j, i = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    mask = np.zeros((h, w), bool)
    mask[i[ok], j[ok]] = True
    return mask


def silhouette(cam, uv: np.ndarray) -> np.ndarray:
    """The filled silhouette of points at pixel coordinates `uv` (eroded by 1 px): a labelled image."""
    from scipy import ndimage

    mask = ndimage.binary_closing(points_mask(cam, uv), np.ones((3, 3), bool), iterations=2)
    mask = ndimage.binary_fill_holes(mask)
    return ndimage.binary_erosion(mask, np.ones((3, 3), bool))


def label_mask(shape: PlanarPoseFit, pose_xyth) -> np.ndarray:
    """Pixels of a shape's silhouette at a known pose: a labelled image."""
    return silhouette(shape.cam, shape.project(pose_xyth))


def fit_colors(samples: dict[str, list[np.ndarray]], required: tuple[str, ...] = ("plain",)) -> dict:
    """Robust RGB Gaussian per region from labelled pixels (two passes: pixels beyond the 99.9 % ellipsoid of
    the first fit, e.g. the pusher in front of the block, are dropped), widened by COLOR_TOLERANCE. Each
    region of `required` must have 10 pixels or more."""
    out = {}
    for region, parts in samples.items():
        x = np.concatenate(parts).astype(np.float64) if parts else np.zeros((0, 3))
        if len(x) < 10:
            continue
        for _ in range(2):
            mean, cov = x.mean(0), np.cov(x.T) + np.eye(3)
            d = x - mean
            keep = np.einsum("ni,ij,nj->n", d, np.linalg.inv(cov), d) < CHI2_3_999
            if keep.sum() >= 10:
                x = x[keep]
        cov = np.cov(x.T) + np.eye(3) * COLOR_TOLERANCE**2
        out[region] = {"mean": x.mean(0).tolist(), "cov": cov.tolist()}
    missing = [r for r in required if r not in out]
    if missing:
        raise ValueError(f"colour calibration: too few labelled pixels of {missing} (e.g. the block outside "
                         "the goal overlay, the rope's marked end)")
    return out


def calibrate_colors(env_kwargs: dict, init_states, camera: str = "front", seed: int = 0,
                     task: str = "push-t") -> dict:
    """The colour model of the task's object from images of the env `env_kwargs` (the real workcell): reset
    to each initial state, label the object's pixels from its true state (as a user labels calibration
    images: push-T's block silhouette at its known pose, the overlay apart; the rope's projected particles,
    its marked end apart) and fit `fit_colors`."""
    import gymnasium

    import twinbench  # noqa: F401 - registers the envs

    labeller, required = _labeller(task)
    env = gymnasium.make(_env_id(task), environment_state=True, **env_kwargs)
    try:
        u = env.unwrapped
        label = labeller(u, u.twin.camera(u.state, camera), camera)
        samples: dict[str, list] = {r: [] for r in required}
        for k, i in enumerate(init_states):
            obs, info = env.reset(seed=seed + k, options={"init_state": int(i)})
            img = obs["pixels"][camera]
            for region, mask in label(info).items():
                samples.setdefault(region, []).append(img[mask])
        return fit_colors(samples, required)
    finally:
        env.close()


def _push_t_labels(u, cam, camera: str):
    est = TPoseEstimator(u.rules.outline, cam, {"plain": {"mean": [0, 0, 0], "cov": np.eye(3).tolist()}})
    overlay = _overlay(u, camera)

    def label(info) -> dict:
        mask = label_mask(est, np.asarray(info["privileged"]["environment_state"][:3], np.float64))
        return {"plain": mask & ~overlay, "overlay": mask & overlay}

    return label


MARK_LABEL_M, BODY_LABEL_M = 0.02, 0.035  # rope particles within / beyond this of the marked end (3 cm red)


def rope_labels(u, cam, table: np.ndarray) -> dict:
    """{"rope", "mark", "table"} pixel masks of the rope in the twin's current state: the pixels of its
    projected particles (the body beyond BODY_LABEL_M of the marked end, the mark within MARK_LABEL_M; in
    between, where the paint changes, neither), and the `table` pixels 3 px or more away from them."""
    from scipy import ndimage

    rope = u.rules.roles["rope"]
    rest = u.twin.rest_particles(rope)
    from_end = rest[:, 0].max() - rest[:, 0]
    pts = u.twin.particles(u.state, rope)

    def mask(points) -> np.ndarray:
        return points_mask(cam, project(cam, points))

    body, mark = mask(pts[from_end > BODY_LABEL_M]), mask(pts[from_end < MARK_LABEL_M])
    near = ndimage.binary_dilation(mask(pts), np.ones((3, 3), bool), iterations=3)
    return {"rope": body & ~mark, "mark": mark & ~body, "table": table & ~near}


def _workspace_xy(u) -> tuple:
    """The task's workspace box (x, y) in env `u`: ((x0, y0), (x1, y1))."""
    (x0, y0, _), (x1, y1, _) = u.rules.settings.workspace
    return (x0, y0), (x1, y1)


def _rope_workspace(u) -> tuple[float, tuple]:
    """(height, workspace) of the rope estimator in env `u`: the rope's centre line above the table (its
    rest particles' mean height) and the task's workspace box (x, y)."""
    return float(np.mean(u.twin.rest_particles(u.rules.roles["rope"])[:, 2])), _workspace_xy(u)


def _rope_labels(u, cam, camera: str):
    table = table_mask(cam, *_rope_workspace(u))
    return lambda info: rope_labels(u, cam, table)


def toy_labels(u, cam, table: np.ndarray) -> dict:
    """{"toy", "box", "table"} pixel masks in the twin's current state: the silhouettes of the toy's torso
    particles and of the box's mesh points (each without the pixels near the other object: the limbs and
    torso differ in colour, the box may hide the toy), and the `table` pixels 3 px or more from both."""
    from scipy import ndimage

    torso, _, box_pts = toy_shapes(u)
    toy = u.twin.particles(u.state, u.rules.roles["toy"])
    box_pose = u.twin.collider_pose(u.state, u.rules.roles["box"])
    box = silhouette(cam, project(cam, box_pts @ box_pose[:3, :3].T + box_pose[:3, 3]))
    whole = silhouette(cam, project(cam, toy)) | points_mask(cam, project(cam, toy))

    def grow(m):
        return ndimage.binary_dilation(m, np.ones((3, 3), bool), iterations=3)

    return {"toy": silhouette(cam, project(cam, toy[torso])) & ~grow(box), "box": box & ~grow(whole),
            "table": table & ~grow(whole | box)}


def _toy_labels(u, cam, camera: str):
    table = table_mask(cam, 0.0, _workspace_xy(u))
    return lambda info: toy_labels(u, cam, table)


def _labeller(task: str):
    table = {"push-t": (_push_t_labels, ("plain",)),
             "rope-routing": (_rope_labels, ("rope", "mark", "table")),
             "toy-packing": (_toy_labels, ("toy", "box", "table"))}
    if task not in table:
        raise InputError(f"perception controllers (policy kind perceive): tasks {sorted(table)}, "
                         f"not {task!r}")
    return table[task]


def _env_id(task: str) -> str:
    from twinbench.tasks import get_task

    return get_task(task).env_id


def _overlay(u, camera: str) -> np.ndarray:
    """The goal overlay's pixels in `camera`'s image (none when the task draws it in another camera)."""
    h, w = u.twin.cameras[camera].output_hw
    if getattr(u.rules, "overlay_camera", None) == camera:
        return np.asarray(u.rules._overlay, bool)
    return np.zeros((h, w), bool)


# ---- the controller ----------------------------------------------------------------------------------
class _PerceptionController:
    """What the perception controllers share: the task's scripted expert, the camera they see through
    (the config's calibrated one, else the env's), the action bounds, a seeded noise stream, the queue of
    estimates that makes the latency. A subclass sets `estimator` and `_start()`s its own state."""

    uses_environment_state = False

    def __init__(self, env, cfg: PerceptionConfig, seed: int, make_expert):
        u = env.unwrapped
        self.cfg, self.seed, self.env = cfg, int(seed), env
        self.expert = make_expert(env)
        self.camera = _camera(cfg.camera_model) if cfg.camera_model else u.twin.camera(u.state, cfg.camera)
        space = env.action_space
        self.low, self.high = np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)

    def reset(self) -> None:
        self.expert.reset()
        self._rng = np.random.default_rng(self.seed)
        self._estimates: deque = deque(maxlen=self.cfg.latency + 1)
        self._step = 0
        self._start()

    def _start(self) -> None:
        """The subclass's own per-episode state."""

    def reseed(self, seed: int) -> None:
        self.seed = int(seed)
        self.reset()


class PerceptionPushT(_PerceptionController):
    """The push-T expert acting on poses estimated from images (see the module docstring)."""

    def __init__(self, env, cfg: PerceptionConfig, seed: int = 0):
        from twinbench.tasks.push_t import make_expert, pose_xytheta

        super().__init__(env, cfg, seed, make_expert)
        u = env.unwrapped
        self.estimator = TPoseEstimator(u.rules.outline, self.camera, cfg.colors, cfg.threshold,
                                        _overlay(u, cfg.camera), cfg.min_pixels)
        self.goal = pose_xytheta(u.rules.goal)
        lo, hi = u.rules.outline.bounds()
        g = np.mgrid[lo[0]:hi[0]:0.005, lo[1]:hi[1]:0.005].reshape(2, -1).T
        self._area = g[u.rules.outline.contains(g, tol=1e-6)]  # footprint samples for the estimated msd
        self.reset()

    def _start(self) -> None:
        self._last: np.ndarray | None = None

    def _msd(self, pose) -> float:
        a = self._area @ _planar(*pose)[:, :2].T + pose[:2]
        b = self._area @ _planar(*self.goal)[:, :2].T + self.goal[:2]
        return float(np.mean(np.sum((a - b) ** 2, axis=1)))

    def select_action(self, obs: dict) -> np.ndarray:
        pusher = np.asarray(obs["agent_pos"], np.float64)[:2]
        if self._step % self.cfg.period == 0:
            est = self.estimator.estimate(obs["pixels"][self.cfg.camera], self._last)
            if est is not None:
                self._last = est
                noisy = est + self._rng.normal(0.0, 1.0, 3) * [self.cfg.noise_m, self.cfg.noise_m,
                                                                self.cfg.noise_rad]
                self._estimates.append(noisy)
        self._step += 1
        if not self._estimates:
            return np.clip(pusher, self.low, self.high).astype(np.float32)  # nothing seen yet: hold
        pose = self._estimates[0]  # `latency` perception steps old once the queue is full
        state = np.r_[pose, self.goal, self._msd(pose)]
        target = np.asarray(self.expert.select_action({"agent_pos": pusher, "environment_state": state}),
                            np.float64)
        action = pusher + self.cfg.gain * (target - pusher)
        return np.clip(action, self.low, self.high).astype(np.float32)


class _PlanOnceController(_PerceptionController):
    """A gripper task's expert that plans once, from the estimate of `latency` perception steps before its
    first action (the robot holds still until then; perception every `period` steps), with the level's
    noise (`_plan_state`). `gain`: the fraction of the expert's position step commanded (orientation and
    gripper as the expert's)."""

    def _start(self) -> None:
        self._state: np.ndarray | None = None

    def _plan_state(self, est: np.ndarray) -> np.ndarray:
        """The expert's `environment_state` from an estimate, with the level's noise."""
        raise NotImplementedError

    def select_action(self, obs: dict) -> np.ndarray:
        ee = np.asarray(obs["agent_pos"], np.float64)
        if self._state is None:
            if self._step % self.cfg.period == 0:
                est = self.estimator.estimate(obs["pixels"][self.cfg.camera])
                if est is not None:
                    self._estimates.append(est)
            self._step += 1
            if len(self._estimates) <= self.cfg.latency:
                return np.clip(ee, self.low, self.high).astype(np.float32)  # not planned yet: hold
            self._state = self._plan_state(self._estimates[0])
        target = np.asarray(self.expert.select_action({"agent_pos": ee, "environment_state": self._state}),
                            np.float64)
        action = target.copy()
        action[:3] = ee[:3] + self.cfg.gain * (target[:3] - ee[:3])
        return np.clip(action, self.low, self.high).astype(np.float32)


class PerceptionRope(_PlanOnceController):
    """The rope-routing expert planning from the rope estimated in the first image(s) (`RopeEstimator`)
    instead of the privileged state, with Gaussian noise `noise_m` on each estimated point and the end's
    direction turned by `noise_rad`; the clip's pose is the twin's (the task's fixed geometry, as push-T's
    goal)."""

    def __init__(self, env, cfg: PerceptionConfig, seed: int = 0):
        from twinbench.tasks.rope_routing import make_expert

        super().__init__(env, cfg, seed, make_expert)
        self.estimator = RopeEstimator(self.camera, cfg.colors, cfg.threshold, cfg.min_pixels,
                                       *_rope_workspace(env.unwrapped))
        self.reset()

    def _plan_state(self, est: np.ndarray) -> np.ndarray:
        """[end, along, centroid, clip x y theta, 0, 0] from an estimate, with the level's noise."""
        u = self.env.unwrapped
        clip = u.twin.collider_pose(u.state, u.rules.roles["clip"])
        end, along, centroid = est[0:3].copy(), est[3:6].copy(), est[6:9].copy()
        a = self._rng.normal(0.0, self.cfg.noise_rad)
        c, s = np.cos(a), np.sin(a)
        along[:2] = end[:2] + np.array([[c, -s], [s, c]]) @ (along[:2] - end[:2])
        for p in (end, along, centroid):
            p[:2] += self._rng.normal(0.0, self.cfg.noise_m, 2)
        return np.r_[end, along, centroid, clip[0, 3], clip[1, 3], np.arctan2(clip[1, 0], clip[0, 0]), 0, 0]


class PerceptionToy(_PlanOnceController):
    """The toy-packing expert planning from the toy's and the box's poses estimated in the first image(s)
    (`ToyEstimator`) instead of the privileged state, with Gaussian noise `noise_m` on each position and
    `noise_rad` on each heading. The toy's origin is taken on the table (z = 0)."""

    def __init__(self, env, cfg: PerceptionConfig, seed: int = 0):
        from twinbench.tasks.toy_packing import make_expert

        super().__init__(env, cfg, seed, make_expert)
        u = env.unwrapped
        _, torso, box = toy_shapes(u)
        self.estimator = ToyEstimator(self.camera, cfg.colors, torso, box, cfg.threshold, cfg.min_pixels,
                                      _workspace_xy(u))
        self.reset()

    def _plan_state(self, est: np.ndarray) -> np.ndarray:
        """[toy x, y, z, theta, box x, y, theta, 0] from an estimate, with the level's noise."""
        sd = np.tile([self.cfg.noise_m, self.cfg.noise_m, self.cfg.noise_rad], 2)
        noise = self._rng.normal(0.0, 1.0, 6) * sd
        toy, box = est[:3] + noise[:3], est[3:] + noise[3:]
        return np.r_[toy[:2], 0.0, toy[2], box, 0.0]


CONTROLLERS = {"push-t": PerceptionPushT, "rope-routing": PerceptionRope, "toy-packing": PerceptionToy}


def make_perceive(spec, task, env, *, seed: int):
    """Policy kind `perceive`: `perceive:CONFIG.json` (a `PerceptionConfig`), the controller of the task."""
    if not spec.target:
        raise InputError(f"policy spec {spec.spec!r}: expected perceive:PATH to a perception config JSON")
    if task.name not in CONTROLLERS:
        raise InputError(f"policy spec {spec.spec!r}: perception controllers exist for "
                         f"{sorted(CONTROLLERS)}, not {task.name!r}")
    return CONTROLLERS[task.name](env, read_config(spec.target), seed=seed)


LEVELS = {
    "push-t": {
        "p0-clean": {},
        "p1-noise1cm": {"noise_m": 0.01, "noise_rad": 0.05},
        "p2-gain0.5": {"gain": 0.5},
        "p3-lag15": {"latency": 15},
        "p4-noise2cm": {"noise_m": 0.02, "noise_rad": 0.1},
        "p5-noise4cm": {"noise_m": 0.04, "noise_rad": 0.2},
        "p6-gain0.2-lag10": {"gain": 0.2, "latency": 10},
        "p7-noise8cm": {"noise_m": 0.08, "noise_rad": 0.4},
    },
    # the rope expert plans once: noise on the planned-from estimate decides the grasp (its fingers close
    # 12 mm from the end, across the rope), the gain how far the arm gets in each leg's steps. Measured in
    # the small study's real workcell (seed 0, grid state 0, one episode each): noise up to 2 cm and gain 0.5
    # succeeded, noise 4 cm and gain 0.25 failed: the ladder spans that transition
    "rope-routing": {
        "r0-clean": {},
        "r1-noise1cm": {"noise_m": 0.01, "noise_rad": 0.1},
        "r2-noise2cm": {"noise_m": 0.02, "noise_rad": 0.2},
        "r3-gain0.4": {"gain": 0.4},
        "r4-noise3cm": {"noise_m": 0.03, "noise_rad": 0.3},
        "r5-gain0.3": {"gain": 0.3},
        "r6-noise4cm": {"noise_m": 0.04, "noise_rad": 0.4},
        "r7-noise6cm": {"noise_m": 0.06, "noise_rad": 0.6},
    },
    # the toy expert plans once too, and packing forgives much: in the small study's real workcell (seed 0,
    # one episode each) the clean controller packed states 0 and 9, 6 cm of noise both, 12 cm state 0 but
    # not 9, 16 cm state 0 (the limbs fold against a wall the toy is pushed into); gain 0.15 packed state 0,
    # gain 0.12 packed both too late for the success window
    "toy-packing": {
        "t0-clean": {},
        "t1-noise4cm": {"noise_m": 0.04, "noise_rad": 0.2},
        "t2-gain0.15": {"gain": 0.15},
        "t3-noise8cm": {"noise_m": 0.08, "noise_rad": 0.4},
        "t4-gain0.12": {"gain": 0.12},
        "t5-noise12cm": {"noise_m": 0.12, "noise_rad": 0.6},
        "t6-noise8cm-gain0.15": {"noise_m": 0.08, "noise_rad": 0.4, "gain": 0.15},
        "t7-noise16cm": {"noise_m": 0.16, "noise_rad": 0.8},
    },
}


def levels(colors: dict, camera_model: dict | None = None,
           task: str = "push-t") -> dict[str, PerceptionConfig]:
    """The study's perception controllers of `task` (`LEVELS`): from the clean controller to ones that
    rarely succeed (noise in the estimate, latency, low gain, slow perception), named by their level."""
    if task not in LEVELS:
        raise InputError(f"perception controllers (policy kind perceive): tasks {sorted(LEVELS)}, "
                         f"not {task!r}")
    base = PerceptionConfig(colors=colors, camera_model=camera_model, period=2)
    return {name: replace(base, extra={"level": name}, **kw) for name, kw in LEVELS[task].items()}


def calibration_camera(calibration: str | Path, camera: str = "front") -> dict:
    """The `camera_model` of a static camera of a calibration file (`construct.calibration`)."""
    from twinbench.construct.calibration import load_calibration

    cams = {c.name: c for c in load_calibration(calibration)}
    if camera not in cams or cams[camera].mount_link is not None:
        raise InputError(f"{calibration}: no static camera {camera!r} (cameras: {sorted(cams)})")
    return camera_dict(cams[camera].view())
