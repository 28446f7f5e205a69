"""Colour alignment (DESIGN §1 step 4, §6): fit the polynomial colour map that turns rendered scan colours
into the real camera's colours, by IRLS with Tukey bi-weights, and apply it to the Gaussians.

The model and its monomial order live in `twinbench.gaussians.colormap` (`polynomial_features`,
`map_colors`, `apply_color_map`); this module only fits it. Pairs are (rendered, real) images of the
same view; optional masks select the pixels of one part (scene, or one object).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from twinbench.gaussians.colormap import map_colors, polynomial_features

TUKEY_C = 4.685  # 95 % efficiency under Gaussian noise


@dataclass
class ColorFit:
    """A fitted map: (3, F) coefficients of `degree`, per-pixel final weights, iterations run."""

    coeffs: np.ndarray
    degree: int
    weights: np.ndarray
    iterations: int
    scale: float  # robust residual scale (sigma) at the last iteration

    def to_json(self) -> dict:
        return {"degree": self.degree, "coeffs": self.coeffs.tolist()}


def _as_pixels(name: str, x) -> np.ndarray:
    a = np.asarray(x)
    if a.dtype == np.uint8:
        a = a.astype(np.float64) / 255.0
    a = np.asarray(a, dtype=np.float64)
    if a.shape[-1:] != (3,):
        raise ValueError(f"{name}: colours must have shape (..., 3), got {a.shape}")
    return a.reshape(-1, 3)


def fit_color_map(
    source,
    target,
    *,
    degree: int = 2,
    mask=None,
    iterations: int = 50,
    robust: bool = True,
    norm_weights: bool = True,
    tukey_c: float = TUKEY_C,
    tol: float = 1e-10,
) -> ColorFit:
    """Fit A (3, F) so that A phi(source) ~ target (colours in [0, 1] or uint8, any shape (..., 3)).

    Weighted least squares on all channels at once (shared weights), pixels weighted by the RGB norm of
    the target (`norm_weights`: dark, noisy pixels count less), then, with `robust`, iteratively
    re-weighted with Tukey bi-weights of the per-pixel residual norm, scale = 1.4826 x median absolute
    residual, for up to `iterations` rounds (stops early when the coefficients change by < tol).
    `robust=False` is plain (norm-weighted) least squares.
    """
    src = _as_pixels("source", source)
    dst = _as_pixels("target", target)
    if src.shape != dst.shape:
        raise ValueError(
            f"source and target must have the same number of pixels, got {src.shape} vs {dst.shape}"
        )
    keep = np.all(np.isfinite(src), 1) & np.all(np.isfinite(dst), 1)
    if mask is not None:
        m = np.asarray(mask).reshape(-1)
        if m.shape[0] != src.shape[0]:
            raise ValueError(f"mask: expected {src.shape[0]} pixels, got {m.shape[0]}")
        keep &= m.astype(bool)
    src, dst = src[keep], dst[keep]
    phi = polynomial_features(src, degree)
    if len(src) < 4 * phi.shape[1]:
        raise ValueError(
            f"colour fit: {len(src)} usable pixels for {phi.shape[1]} coefficients per channel; "
            "give more pixels (or a lower degree)"
        )
    base_w = np.linalg.norm(dst, axis=1) if norm_weights else np.ones(len(src))
    base_w = np.maximum(base_w, 1e-3)

    def solve(w):
        sw = np.sqrt(w)[:, None]
        sol, *_ = np.linalg.lstsq(phi * sw, dst * sw, rcond=None)
        return sol.T

    coeffs = solve(base_w)
    w = base_w
    scale = float("nan")
    it = 0
    if robust:
        while it < iterations:
            it += 1
            r = np.linalg.norm(phi @ coeffs.T - dst, axis=1)
            scale = max(1.4826 * float(np.median(r)), 1e-6)
            u = r / (tukey_c * scale)
            tukey = np.where(u < 1.0, (1.0 - u**2) ** 2, 0.0)
            w = base_w * tukey
            if np.count_nonzero(w) < 4 * phi.shape[1]:
                break
            new = solve(w)
            delta = float(np.max(np.abs(new - coeffs)))
            coeffs = new
            if delta < tol:
                break
    weights = np.zeros(keep.shape[0])
    weights[keep] = w
    return ColorFit(coeffs=coeffs, degree=degree, weights=weights, iterations=it, scale=scale)


# ------------------------------------------------------------------------------------------------
# pair folders and the before/after grid


def read_image(path: Path) -> np.ndarray:
    """An RGB uint8 image (alpha dropped; grey expanded)."""
    import imageio.v3 as iio

    try:
        img = np.asarray(iio.imread(path))
    except Exception as exc:  # noqa: BLE001 - any decoder failure is a bad file
        raise ValueError(f"{path}: cannot read the image ({exc})") from exc
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    if img.ndim != 3 or img.shape[2] not in (3, 4):
        raise ValueError(f"{path}: expected an RGB(A) image, got shape {img.shape}")
    if img.dtype != np.uint8:
        raise ValueError(f"{path}: expected 8-bit colour, got {img.dtype}")
    return img[..., :3]


def find_pairs(folder) -> list[tuple[str, Path, Path, Path | None]]:
    """(name, rendered, real, mask or None) for every NAME_render.png with a NAME_real.png beside it
    (NAME_mask.png optional: non-zero = use the pixel)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"pairs folder not found: {folder}")
    out = []
    for render in sorted(folder.glob("*_render.png")):
        name = render.name[: -len("_render.png")]
        real = folder / f"{name}_real.png"
        if not real.is_file():
            raise FileNotFoundError(f"{render}: its real image {real.name} is missing")
        mask = folder / f"{name}_mask.png"
        out.append((name, render, real, mask if mask.is_file() else None))
    if not out:
        raise FileNotFoundError(
            f"{folder}: no NAME_render.png / NAME_real.png pairs (optional NAME_mask.png) found"
        )
    return out


def load_pairs(folder) -> list[tuple[str, np.ndarray, np.ndarray, np.ndarray | None]]:
    """Images of `find_pairs`, checked for equal sizes."""
    pairs = []
    for name, rp, qp, mp in find_pairs(folder):
        r, q = read_image(rp), read_image(qp)
        if r.shape != q.shape:
            raise ValueError(f"{qp}: size {q.shape[:2]} differs from {rp.name} {r.shape[:2]}")
        m = None
        if mp is not None:
            m = read_image(mp)[..., 0] > 0
            if m.shape != r.shape[:2]:
                raise ValueError(f"{mp}: size {m.shape} differs from {rp.name} {r.shape[:2]}")
        pairs.append((name, r, q, m))
    return pairs


def fit_pairs(pairs, *, degree: int = 2, iterations: int = 50, robust: bool = True) -> ColorFit:
    """One map fitted on every pair's (masked) pixels together."""
    src = np.concatenate([p[1].reshape(-1, 3) for p in pairs])
    dst = np.concatenate([p[2].reshape(-1, 3) for p in pairs])
    masks = [np.ones(p[1].shape[:2], bool) if p[3] is None else p[3] for p in pairs]
    mask = np.concatenate([m.reshape(-1) for m in masks])
    return fit_color_map(src, dst, degree=degree, mask=mask, iterations=iterations, robust=robust)


def map_image(img: np.ndarray, coeffs, degree: int) -> np.ndarray:
    """Apply a colour map to an image's pixels (uint8 in and out, clamped)."""
    out = map_colors(img.reshape(-1, 3).astype(np.float64) / 255.0, coeffs, degree)
    return (np.clip(out, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8).reshape(img.shape)


def before_after_grid(pairs, coeffs, degree: int) -> np.ndarray:
    """One row per pair: rendered (before) | real | rendered mapped (after), uint8."""
    rows = []
    for _, render, real, _ in pairs:
        rows.append(np.concatenate([render, real, map_image(render, coeffs, degree)], axis=1))
    width = max(r.shape[1] for r in rows)
    rows = [np.pad(r, ((0, 0), (0, width - r.shape[1]), (0, 0))) for r in rows]
    return np.concatenate(rows, axis=0)


# ------------------------------------------------------------------------------------------------
# files: rendered pairs and the align-color output folder


def render_pairs(scan_files, calibration: Path, real_dir: Path, out_dir: Path,
                 background=(0.0, 0.0, 0.0)) -> list[str]:
    """Render the Gaussians from each static calibrated camera (its output view) beside its real image
    REAL_DIR/NAME.png: writes OUT_DIR/NAME_render.png, NAME_real.png and NAME_mask.png (pixels the scan
    covers, alpha > 0.99). Returns the camera names."""
    import shutil

    import imageio.v3 as iio

    from twinbench.construct.calibration import load_calibration
    from twinbench.gaussians.cloud import GaussianCloud
    from twinbench.gaussians.io import load_gaussians
    from twinbench.gaussians.render import render

    cloud = GaussianCloud.concatenate([load_gaussians(p) for p in scan_files])
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    names = []
    for cam in load_calibration(calibration):
        real = Path(real_dir) / f"{cam.name}.png"
        if cam.mount_link is not None or not real.is_file():
            continue
        img = read_image(real)
        h, w = cam.output_hw
        if img.shape[:2] != (h, w):
            raise ValueError(f"{real}: size {img.shape[:2]} differs from camera output_hw {(h, w)}")
        out = render(cloud, [cam.view()], background=background)[0]
        iio.imwrite(out_dir / f"{cam.name}_render.png", out.rgb_uint8())
        iio.imwrite(out_dir / f"{cam.name}_mask.png", ((out.alpha > 0.99) * 255).astype(np.uint8))
        shutil.copyfile(real, out_dir / f"{cam.name}_real.png")
        names.append(cam.name)
    if not names:
        raise ValueError(f"{real_dir}: no real image NAME.png for any static camera of {calibration}")
    return names


def align_color_files(pairs_dir, out, gaussians=(), *, degree: int = 2,
                      iterations: int = 50) -> tuple[int, ColorFit]:
    """`twinbench align-color`: fit one colour map on a pairs folder and write OUT/color_map.json,
    OUT/grid.png (before | real | after) and each of `gaussians` (.ply) mapped, as OUT/<its name>.
    Returns (number of pairs, the fit)."""
    import imageio.v3 as iio

    from twinbench.construct._json import write_json
    from twinbench.gaussians.colormap import apply_color_map
    from twinbench.gaussians.io import load_gaussians, save_gaussians

    out = Path(out)
    pairs = load_pairs(pairs_dir)
    fit = fit_pairs(pairs, degree=degree, iterations=iterations)
    write_json(out / "color_map.json", fit.to_json())
    iio.imwrite(out / "grid.png", before_after_grid(pairs, fit.coeffs, fit.degree))
    for p in gaussians:
        save_gaussians(apply_color_map(load_gaussians(p), fit.coeffs, fit.degree), out / Path(p).name)
    return len(pairs), fit
