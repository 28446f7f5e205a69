"""What every renderer backend shares: the rules it renders by (DESIGN §6) and what it returns.

EWA projection with a 0.3 px low-pass added to the 2D covariance, 16x16 tiles, front-to-back compositing by
camera depth, alpha = min(0.99, o exp(-d^2/2)), skip alpha < 1/255, stop a pixel before the Gaussian that
would bring its transmittance below 1e-4; Gaussians closer than NEAR to the camera plane are culled.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TILE = 16
NEAR = 0.01
LOW_PASS = 0.3  # px^2 added to the 2D covariance diagonal
ALPHA_MAX = 0.99
ALPHA_MIN = 1.0 / 255.0
T_MIN = 1.0e-4


@dataclass
class RenderOutput:
    """Float32 images: rgb (H, W, 3) in [0, 1], depth (H, W) (alpha-normalised expected camera z,
    0 where nothing is drawn), alpha (H, W) = 1 - final transmittance. Lists of cameras give lists."""

    rgb: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray

    def rgb_uint8(self) -> np.ndarray:
        """rgb as H x W x 3 uint8 (rounded)."""
        scaled = self.rgb * np.float32(255.0)  # one temporary, rounded and clipped in place
        np.rint(scaled, out=scaled)
        np.clip(scaled, 0, 255, out=scaled)
        return scaled.astype(np.uint8)
