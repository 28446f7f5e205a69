"""A camera's response: what a real camera does to the light the renderer computes (optics, sensor, ISP).

    response = CameraResponse(matrix=..., gamma=1.1, vignetting=0.2, noise_std=2.0, blur_sigma=0.6)
    image = response.apply(rendered_uint8_hwc, np.random.default_rng(seed))

Applied in this order to colours in [0, 1]: Gaussian blur (`blur_sigma`, pixels), vignetting (the image
darkened by the factor 1 - `vignetting` * (r / r_corner)^2, r the distance from the image centre), white
balance (per-channel gains), the 3x3 colour `matrix` and `offset` (out = matrix @ in + offset), clipping
to [0, 1], `gamma` (out = in ** gamma), sensor noise (normal, `noise_std` in 0-255 levels), rounding to
uint8. The default is the identity (the image is returned unchanged). A twin's camera may carry one
(`CameraSpec.response`); TwinEnv applies it to every image of that camera.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, fields

import numpy as np


def _vector(name: str, value, shape: tuple, default) -> np.ndarray:
    a = np.asarray(default if value is None else value, dtype=np.float64)
    if a.shape != shape or not np.all(np.isfinite(a)):
        raise ValueError(f"camera response.{name}: expected finite values of shape {shape}, got {a.shape}")
    a = a.copy()
    a.flags.writeable = False
    return a


@functools.lru_cache(maxsize=16)
def _falloff(h: int, w: int, vignetting: float) -> np.ndarray:
    """The vignetting factor 1 - v * (r / r_corner)^2 of an (h, w) image, (h, w, 1) float32 (kept: the same
    for every image of a camera)."""
    yy, xx = np.mgrid[0:h, 0:w]
    cx, cy = (w - 1) / 2, (h - 1) / 2
    r2 = ((xx - cx) ** 2 + (yy - cy) ** 2) / max(cx**2 + cy**2, 1.0)
    out = (1.0 - vignetting * r2).astype(np.float32)[..., None]
    out.flags.writeable = False
    return out


@dataclass(frozen=True, eq=False)
class CameraResponse:
    """See the module docstring; every field's default leaves images unchanged."""

    matrix: np.ndarray = field(default_factory=lambda: np.eye(3))
    offset: np.ndarray = field(default_factory=lambda: np.zeros(3))
    gamma: float = 1.0
    white_balance: np.ndarray = field(default_factory=lambda: np.ones(3))
    vignetting: float = 0.0
    noise_std: float = 0.0
    blur_sigma: float = 0.0

    def __post_init__(self) -> None:
        for name, shape, neutral in (("matrix", (3, 3), np.eye(3)), ("offset", (3,), np.zeros(3)),
                                     ("white_balance", (3,), np.ones(3))):
            object.__setattr__(self, name, _vector(name, getattr(self, name), shape, neutral))
        for name, lo, hi in (("gamma", 1e-3, 10.0), ("vignetting", 0.0, 1.0), ("noise_std", 0.0, 255.0),
                             ("blur_sigma", 0.0, 50.0)):
            v = float(getattr(self, name))
            if not (np.isfinite(v) and lo <= v <= hi):
                raise ValueError(f"camera response.{name}: expected a number in [{lo}, {hi}], got {v!r}")
            object.__setattr__(self, name, v)
        if np.any(self.white_balance <= 0):
            raise ValueError(f"camera response.white_balance: gains must be > 0, got {self.white_balance}")

    @property
    def is_identity(self) -> bool:
        return (np.array_equal(self.matrix, np.eye(3)) and not self.offset.any() and self.gamma == 1.0
                and np.all(self.white_balance == 1.0) and self.vignetting == 0.0 and self.noise_std == 0.0
                and self.blur_sigma == 0.0)

    def map_colors(self, rgb) -> np.ndarray:
        """The colour part alone (white balance, matrix + offset, clip, gamma) of colours (..., 3) in [0, 1]:
        what the camera makes of a colour at the image centre, without noise. float32 input stays float32
        (images), anything else is computed in float64."""
        x = np.asarray(rgb)
        dt = np.float32 if x.dtype == np.float32 else np.float64
        # white balance folded into the matrix: (x * wb) @ M.T == x @ (M * wb).T
        m = (self.matrix * self.white_balance).T.astype(dt)
        x = x.astype(dt, copy=False) @ m + self.offset.astype(dt)
        np.clip(x, 0.0, 1.0, out=x)
        if self.gamma == 1.0:
            return x
        with np.errstate(divide="ignore"):  # x ** gamma as exp(gamma log x): vectorised, 0 stays 0
            np.log(x, out=x)
        x *= dt(self.gamma)
        return np.exp(x, out=x)

    def apply(self, image, rng: np.random.Generator | None = None) -> np.ndarray:
        """The camera's image of a rendered uint8 (H, W, 3) image; `rng` draws the sensor noise (needed
        when `noise_std` > 0)."""
        img = np.asarray(image)
        if img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
            raise ValueError(f"camera response: expected a uint8 (H, W, 3) image, got {img.dtype} "
                             f"{img.shape}")
        if self.is_identity:
            return img
        if self.noise_std > 0 and rng is None:
            raise ValueError("camera response: noise_std > 0 needs a random generator (rng)")
        x = img.astype(np.float32) * np.float32(1.0 / 255.0)  # float32 throughout: images, not physics
        if self.blur_sigma > 0:
            from scipy.ndimage import gaussian_filter

            x = gaussian_filter(x, sigma=(self.blur_sigma, self.blur_sigma, 0.0), mode="nearest")
        if self.vignetting > 0:
            x *= _falloff(x.shape[0], x.shape[1], self.vignetting)
        x = self.map_colors(x)
        x *= np.float32(255.0)
        if self.noise_std > 0:
            x += rng.standard_normal(x.shape, dtype=np.float32) * np.float32(self.noise_std)
        x += np.float32(0.5)
        return np.clip(x, 0, 255, out=x).astype(np.uint8)

    def to_dict(self) -> dict:
        return {f.name: (v.tolist() if isinstance(v := getattr(self, f.name), np.ndarray) else v)
                for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> CameraResponse:
        """From `to_dict`'s fields (any may be omitted: identity)."""
        names = [f.name for f in fields(cls)]
        if not isinstance(d, dict):
            raise ValueError(f"camera response: expected an object with fields {names}")
        unknown = sorted(set(d) - set(names))
        if unknown:
            raise ValueError(f"camera response: unknown field(s) {unknown}; known: {names}")
        return cls(**d)
