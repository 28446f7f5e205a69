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


def _planar(x: float, y: float, th: float) -> np.ndarray:
    c, s = np.cos(th), np.sin(th)
    return np.array([[c, -s, x], [s, c, y]])


class TPoseEstimator:
    """Segments a block of footprint `outline` by colour in one camera's images and fits its planar pose."""

    def __init__(self, outline, camera, colors: dict, threshold: float = CHI2_3_999,
                 overlay: np.ndarray | None = None, min_pixels: int = 20):
        self.outline, self.cam = outline, camera
        self.threshold, self.min_pixels = float(threshold), int(min_pixels)
        self.overlay = None if overlay is None else np.asarray(overlay, bool)
        self.models = {}
        for region, m in colors.items():
            cov = np.asarray(m["cov"], np.float64) + np.eye(3) * 1e-3
            self.models[region] = (np.asarray(m["mean"], np.float64), np.linalg.inv(cov))
        self.points = _solid_points(outline)
        self._w2c = camera.world_to_cam

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
            mean, icov = self.models.get(region, self.models["plain"])
            d = img[where] - mean
            mask[where] = np.einsum("ni,ij,nj->n", d, icov, d) < self.threshold
        mask = ndimage.binary_opening(mask, np.ones((3, 3), bool))
        labels, n = ndimage.label(mask)
        if n == 0:
            return mask
        sizes = np.bincount(labels.ravel())[1:]
        return labels == (1 + int(np.argmax(sizes)))

    # -- pose
    def project(self, pose_xyth) -> np.ndarray:
        """Pixel (u, v) of the solid's points at planar pose (x, y, theta), (N, 2)."""
        m = _planar(*pose_xyth)
        xy = self.points[:, :2] @ m[:, :2].T + m[:, 2]
        world = np.c_[xy, self.points[:, 2]]
        p = world @ self._w2c[:3, :3].T + self._w2c[:3, 3]
        z = np.maximum(p[:, 2], 1e-6)
        return np.c_[self.cam.fx * p[:, 0] / z + self.cam.cx, self.cam.fy * p[:, 1] / z + self.cam.cy]

    def _table_points(self, uv: np.ndarray, z: float) -> np.ndarray:
        """Back-projection of pixels onto the plane at height z (world xy)."""
        c2w = self.cam.cam_to_world
        rays = np.c_[(uv[:, 0] - self.cam.cx) / self.cam.fx, (uv[:, 1] - self.cam.cy) / self.cam.fy,
                     np.ones(len(uv))] @ c2w[:3, :3].T
        t = (z - c2w[2, 3]) / rays[:, 2]
        return (c2w[:3, 3] + t[:, None] * rays)[:, :2]

    def estimate(self, image: np.ndarray, previous=None) -> np.ndarray | None:
        """(x, y, theta) of the block, or None when fewer than `min_pixels` of its colour are seen.
        `previous`: a recent estimate to start from (else 12 headings, the best 3 refined). The fit
        minimises the mean signed distance (pixels, negative inside) of the projected solid's points to the
        blob's edge."""
        from scipy import ndimage
        from scipy.optimize import minimize

        mask = self.segment(image)
        ii, jj = np.nonzero(mask)
        if len(ii) < self.min_pixels:
            return None
        sdf = ndimage.distance_transform_edt(~mask) - ndimage.distance_transform_edt(mask)
        h, w = mask.shape

        def cost(p):
            uv = self.project(p) - 0.5  # pixel centres at integer coordinates
            d = ndimage.map_coordinates(sdf, [np.clip(uv[:, 1], 0, h - 1), np.clip(uv[:, 0], 0, w - 1)],
                                        order=1, mode="nearest")
            return float(np.mean(np.minimum(d, 20.0)))

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
        uv = np.c_[jj + 0.5, ii + 0.5]
        centre = self._table_points(uv, 0.5 * self.outline.height).mean(0)
        starts = [np.r_[centre, th] for th in np.linspace(-np.pi, np.pi, 12, endpoint=False)]
        costs = [cost(s) for s in starts]
        fits = [refine(starts[k], 0.01) for k in np.argsort(costs)[:3]]  # the 3 best headings, refined
        return min(fits, key=lambda f: f[1])[0]


# ---- colour calibration -----------------------------------------------------------------------------------
def label_mask(estimator: TPoseEstimator, pose_xyth) -> np.ndarray:
    """Pixels of the block's silhouette at a known pose (eroded by 1 px): a labelled image."""
    from scipy import ndimage

    h, w = estimator.cam.height, estimator.cam.width
    mask = np.zeros((h, w), bool)
    uv = estimator.project(pose_xyth)
    j, i = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
    ok = (i >= 0) & (i < h) & (j >= 0) & (j < w)
    mask[i[ok], j[ok]] = True
    mask = ndimage.binary_closing(mask, np.ones((3, 3), bool), iterations=2)
    mask = ndimage.binary_fill_holes(mask)
    return ndimage.binary_erosion(mask, np.ones((3, 3), bool))


def fit_colors(samples: dict[str, list[np.ndarray]]) -> dict:
    """Robust RGB Gaussian per region from labelled pixels (two passes: pixels beyond the 99.9 % ellipsoid of
    the first fit, e.g. the pusher in front of the block, are dropped), widened by COLOR_TOLERANCE."""
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
    if "plain" not in out:
        raise ValueError("colour calibration: too few labelled block pixels outside the goal overlay")
    return out


def calibrate_colors(env_kwargs: dict, init_states, camera: str = "front", seed: int = 0) -> dict:
    """The T's colour model from images of the env `env_kwargs` (the real workcell): reset to each initial
    state, label the block's pixels from its known pose (as a user labels calibration images) and fit
    `fit_colors`."""
    import gymnasium

    import twinbench  # noqa: F401 - registers the envs

    env = gymnasium.make("twinbench/PushT-v0", environment_state=True, **env_kwargs)
    try:
        u = env.unwrapped
        cam = u.twin.camera(u.state, camera)
        est = TPoseEstimator(u.rules.outline, cam, {"plain": {"mean": [0, 0, 0], "cov": np.eye(3).tolist()}})
        overlay = _overlay(u, camera)
        samples: dict[str, list] = {"plain": [], "overlay": []}
        for k, i in enumerate(init_states):
            obs, info = env.reset(seed=seed + k, options={"init_state": int(i)})
            pose = np.asarray(info["privileged"]["environment_state"][:3], np.float64)
            mask = label_mask(est, pose)
            img = obs["pixels"][camera]
            samples["plain"].append(img[mask & ~overlay])
            samples["overlay"].append(img[mask & overlay])
        return fit_colors(samples)
    finally:
        env.close()


def _overlay(u, camera: str) -> np.ndarray:
    """The goal overlay's pixels in `camera`'s image (none when the task draws it in another camera)."""
    h, w = u.twin.cameras[camera].output_hw
    if getattr(u.rules, "overlay_camera", None) == camera:
        return np.asarray(u.rules._overlay, bool)
    return np.zeros((h, w), bool)


# ---- the controller ----------------------------------------------------------------------------------
class PerceptionPushT:
    """The push-T expert acting on poses estimated from images (see the module docstring)."""

    uses_environment_state = False

    def __init__(self, env, cfg: PerceptionConfig, seed: int = 0):
        from twinbench.tasks.push_t import make_expert, pose_xytheta

        u = env.unwrapped
        self.cfg, self.seed = cfg, int(seed)
        self.expert = make_expert(env)
        cam = _camera(cfg.camera_model) if cfg.camera_model else u.twin.camera(u.state, cfg.camera)
        self.estimator = TPoseEstimator(u.rules.outline, cam, cfg.colors, cfg.threshold,
                                        _overlay(u, cfg.camera), cfg.min_pixels)
        self.goal = pose_xytheta(u.rules.goal)
        lo, hi = u.rules.outline.bounds()
        g = np.mgrid[lo[0]:hi[0]:0.005, lo[1]:hi[1]:0.005].reshape(2, -1).T
        self._area = g[u.rules.outline.contains(g, tol=1e-6)]  # footprint samples for the estimated msd
        space = env.action_space
        self.low, self.high = np.asarray(space.low, np.float64), np.asarray(space.high, np.float64)
        self.reset()

    def reset(self) -> None:
        self.expert.reset()
        self._rng = np.random.default_rng(self.seed)
        self._estimates: deque = deque(maxlen=self.cfg.latency + 1)
        self._last: np.ndarray | None = None
        self._step = 0

    def reseed(self, seed: int) -> None:
        self.seed = int(seed)
        self.reset()

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


def make_perceive(spec, task, env, *, seed: int):
    """Policy kind `perceive`: `perceive:CONFIG.json` (a `PerceptionConfig`)."""
    if not spec.target:
        raise InputError(f"policy spec {spec.spec!r}: expected perceive:PATH to a perception config JSON")
    if task.name != "push-t":
        raise InputError(f"policy spec {spec.spec!r}: perception controllers exist for push-t only, "
                         f"not {task.name!r}")
    return PerceptionPushT(env, read_config(spec.target), seed=seed)


def levels(colors: dict, camera_model: dict | None = None) -> dict[str, PerceptionConfig]:
    """The study's perception controllers: from the clean controller to ones that rarely succeed (noise in
    the estimate, latency, low gain, slow perception), named by their level."""
    base = PerceptionConfig(colors=colors, camera_model=camera_model, period=2)
    table = {
        "p0-clean": {},
        "p1-noise1cm": {"noise_m": 0.01, "noise_rad": 0.05},
        "p2-gain0.5": {"gain": 0.5},
        "p3-lag15": {"latency": 15},
        "p4-noise2cm": {"noise_m": 0.02, "noise_rad": 0.1},
        "p5-noise4cm": {"noise_m": 0.04, "noise_rad": 0.2},
        "p6-gain0.2-lag10": {"gain": 0.2, "latency": 10},
        "p7-noise8cm": {"noise_m": 0.08, "noise_rad": 0.4},
    }
    return {name: replace(base, extra={"level": name}, **kw) for name, kw in table.items()}


def twin_camera(twin_dir: str | Path, camera: str = "front") -> dict:
    """The `camera_model` of a twin directory's camera (as its env places it at the start configuration)."""
    import gymnasium

    import twinbench  # noqa: F401 - registers the envs

    env = gymnasium.make("twinbench/PushT-v0", twin=str(twin_dir))
    try:
        u = env.unwrapped
        return camera_dict(u.twin.camera(u.state, camera))
    finally:
        env.close()
