"""Camera refinement: each static camera's pose and intrinsics, from its calibration, corrected so that the
aligned scan rendered through it lines up with the camera's real image.

    fits = refine_camera_files(["aligned/robot.ply", ...], "calibration.json", "real/", "cameras/")

A calibration a few tenths of a degree, a few millimetres and half a percent of focal length off moves the
scene by several pixels in a 240 px policy image; a twin rendered through it shows the policy another view
than the real camera does. The real image fixes it: render the scan (world frame, after `align-robot`)
through the candidate camera, fit an affine colour map (rendered -> real, the scan's colours are in another
colour space) on the pixels the scan covers, and minimise the remaining squared difference over the camera's
rotation and translation (in its own frame) and its fx, fy, cx, cy (Powell), on images blurred by
`BLURS` px in turn (coarse to fine: a wide basin first). `PRIOR` pulls weakly toward the calibration, which
settles the directions the image cannot tell apart (a small turn vs a shifted principal point).

Only static cameras with a real image NAME.png are refined; the others (a wrist camera's hand-eye pose)
are kept as calibrated. The scan must cover most of the image (`MIN_COVERAGE`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

# one unit of the search in each parameter: about a pixel's move of a 240 px image a metre away
UNITS = {"rotation_deg": 0.1, "translation_m": 0.002, "focal_rel": 0.0025, "principal_px": 1.0}
BLURS = (3.0, 1.5, 0.7)  # px, coarse to fine
PRIOR = 1e-3  # weight of the squared parameter change (in units) against the image residual (1 at the start)
MIN_COVERAGE = 0.2  # of the image's pixels the scan must cover (opaque: alpha > 0.99)


@dataclasses.dataclass(frozen=True)
class CameraFit:
    """A refined camera and how far the refinement moved it."""

    camera: object  # CameraSpec
    rms_before: float  # colour-fitted residual on the sharpest blur, 0-255 levels: calibration ...
    rms_after: float  # ... and refined camera
    rotation_deg: float
    translation_m: float
    intrinsics_change: tuple[float, float, float, float]  # fx, fy (relative), cx, cy (sensor px)
    shift_px: float  # median move of the scan's points in the image, calibration -> refined
    evaluations: int
    adopted: bool  # False: the refinement did not lower the residual, the calibration is kept

    def to_json(self) -> dict:
        return {"rms_before": round(float(self.rms_before), 3), "rms_after": round(float(self.rms_after), 3),
                "rotation_deg": round(self.rotation_deg, 4), "translation_m": round(self.translation_m, 5),
                "intrinsics_change": {k: round(float(v), 5) for k, v in
                                      zip(("fx_rel", "fy_rel", "cx_px", "cy_px"), self.intrinsics_change,
                                          strict=True)},
                "shift_px": round(self.shift_px, 3), "evaluations": self.evaluations, "adopted": self.adopted}


def moved_camera(cam, x: np.ndarray):
    """`cam` (a CameraSpec) moved by the 10 search parameters `x` (in `UNITS`): rotation vector, translation
    (camera frame), fx, fy (relative), cx, cy."""
    from scipy.spatial.transform import Rotation

    x = np.asarray(x, np.float64)
    d = np.eye(4)
    d[:3, :3] = Rotation.from_rotvec(np.radians(UNITS["rotation_deg"] * x[:3])).as_matrix()
    d[:3, 3] = UNITS["translation_m"] * x[3:6]
    fx, fy, cx, cy = cam.intrinsics
    k = (fx * (1.0 + UNITS["focal_rel"] * x[6]), fy * (1.0 + UNITS["focal_rel"] * x[7]),
         cx + UNITS["principal_px"] * x[8], cy + UNITS["principal_px"] * x[9])
    return dataclasses.replace(cam, pose=np.asarray(cam.pose) @ d, intrinsics=k)


def image_shift(cam, other, points: np.ndarray) -> np.ndarray:
    """Distance (output px) between where cameras `cam` and `other` (CameraSpecs of one output size) put
    each of the world `points` that `other` sees in its image."""
    from twinbench.gaussians.reference import project_means

    points = np.asarray(points, np.float64)
    (a, _), (b, depth) = project_means(points, cam.view()), project_means(points, other.view())
    h, w = other.output_hw
    seen = (depth > 0) & (b[:, 0] >= 0) & (b[:, 0] < w) & (b[:, 1] >= 0) & (b[:, 1] < h)
    return np.linalg.norm(a[seen] - b[seen], axis=1)


def _blur(img: np.ndarray, sigma: float) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    return gaussian_filter(img, (sigma, sigma, 0)) if sigma > 0 else img


def colour_fitted_residual(cloud, cam, real: np.ndarray, blur: float) -> tuple[np.ndarray, np.ndarray]:
    """(residual image (H, W, 3), mask of the pixels the scan covers) of `real` (float RGB in [0, 1]) minus
    the render of `cloud` through `cam` under the best affine colour map, both blurred by `blur` px."""
    from twinbench.gaussians.render import render

    out = render(cloud, [cam.view()])[0]
    mask = np.asarray(out.alpha) > 0.99
    rendered = _blur(np.asarray(out.rgb, np.float64), blur)[mask]
    target = _blur(real, blur)[mask]
    design = np.c_[np.ones(len(rendered)), rendered]
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    res = np.zeros(real.shape)
    res[mask] = design @ coef - target
    return res, mask


def refine_camera(cloud, cam, real: np.ndarray, *, blurs=BLURS, prior: float = PRIOR,
                  max_evals: int = 1000) -> CameraFit:
    """Refine a static camera (CameraSpec) on its real image `real` (uint8 or float RGB, the camera's
    output size) of the Gaussians `cloud` (world frame); at most `max_evals` renders per blur."""
    from scipy.optimize import minimize
    from scipy.spatial.transform import Rotation

    real = np.asarray(real)
    real = real / 255.0 if real.dtype == np.uint8 else real.astype(np.float64)
    if real.shape[:2] != tuple(cam.output_hw):
        raise ValueError(f"camera {cam.name!r}: real image size {real.shape[:2]} differs from its output_hw "
                         f"{tuple(cam.output_hw)}")
    _, mask = colour_fitted_residual(cloud, cam, real, 0.0)
    if mask.mean() < MIN_COVERAGE:
        raise ValueError(f"camera {cam.name!r}: the scan covers {mask.mean():.0%} of its image (at least "
                         f"{MIN_COVERAGE:.0%} needed): check the calibration's pose and the scan's alignment")

    def mse(x, blur):
        res, m = colour_fitted_residual(cloud, moved_camera(cam, x), real, blur)
        if m.mean() < MIN_COVERAGE:  # a camera turned off the scan: a few pixels would fit too well
            return 1.0
        return float(np.mean(res[m] ** 2))

    x, evals = np.zeros(10), 0
    for blur in blurs:
        start = mse(x, blur)

        def cost(v, blur=blur, start=start):
            return mse(v, blur) / max(start, 1e-12) + prior * float(v @ v)

        fit = minimize(cost, x, method="Powell", options={"xtol": 0.05, "ftol": 1e-4, "maxfev": max_evals})
        x, evals = fit.x, evals + int(fit.nfev) + 1
    sharp = blurs[-1]
    before, after = np.sqrt(mse(np.zeros(10), sharp)), np.sqrt(mse(x, sharp))
    adopted = bool(after < before)
    if not adopted:
        x, after = np.zeros(10), before
    moved = moved_camera(cam, x)
    rel = np.linalg.inv(cam.pose) @ moved.pose
    k0, k1 = np.asarray(cam.intrinsics), np.asarray(moved.intrinsics)
    return CameraFit(camera=moved, rms_before=255.0 * before, rms_after=255.0 * after,
                     rotation_deg=float(np.degrees(Rotation.from_matrix(rel[:3, :3]).magnitude())),
                     translation_m=float(np.linalg.norm(rel[:3, 3])),
                     intrinsics_change=(*(k1[:2] / k0[:2] - 1.0), *(k1[2:] - k0[2:])),
                     shift_px=float(np.median(image_shift(moved, cam, cloud.means))),
                     evaluations=evals, adopted=adopted)


def residual_strip(cloud, before, after, real: np.ndarray) -> np.ndarray:
    """uint8 image: real | |residual| through `before` | |residual| through `after` (x4, unblurred)."""
    real = np.asarray(real)
    realf = real / 255.0 if real.dtype == np.uint8 else real
    panels = [realf]
    for cam in (before, after):
        res, _ = colour_fitted_residual(cloud, cam, realf, 0.0)
        panels.append(np.clip(4.0 * np.abs(res), 0.0, 1.0))
    return (255.0 * np.concatenate(panels, axis=1)).round().astype(np.uint8)


def refine_camera_files(scan_files, calibration, real_dir, out, **kwargs) -> dict[str, CameraFit]:
    """`twinbench refine-cameras`: refine each static camera of CALIBRATION that has a real image
    REAL_DIR/NAME.png against the Gaussians of `scan_files` (world frame); writes OUT/calibration.json (every
    camera: refined or as given), OUT/refine.json (each fit) and OUT/NAME_residual.png (real | residual
    before | after). Returns the fits by camera name."""
    import imageio.v3 as iio

    from twinbench.construct._json import write_json
    from twinbench.construct.align_color import read_image
    from twinbench.construct.calibration import calibration_doc, load_calibration
    from twinbench.gaussians.cloud import GaussianCloud
    from twinbench.gaussians.io import load_gaussians

    cloud = GaussianCloud.concatenate([load_gaussians(p) for p in scan_files])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cameras, fits = [], {}
    for cam in load_calibration(calibration):
        path = Path(real_dir) / f"{cam.name}.png"
        if cam.mount_link is None and path.is_file():
            img = read_image(path)
            try:
                fit = refine_camera(cloud, cam, img, **kwargs)
            except ValueError as exc:
                raise ValueError(f"{path}: {exc}") from exc
            fits[cam.name] = fit
            iio.imwrite(out / f"{cam.name}_residual.png", residual_strip(cloud, cam, fit.camera, img))
            cam = fit.camera
        cameras.append(cam)
    if not fits:
        raise ValueError(f"{real_dir}: no real image NAME.png for any static camera of {calibration}")
    write_json(out / "calibration.json", calibration_doc(cameras))
    write_json(out / "refine.json", {name: f.to_json() for name, f in fits.items()})
    return fits
