"""GaussianCloud: the 3D Gaussian Splatting data object (host arrays, float32)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def sh_coeffs_for_degree(degree: int) -> int:
    """Number of SH coefficients per colour channel for a degree (0..3)."""
    return (degree + 1) ** 2


@dataclass
class GaussianCloud:
    """N Gaussians. Quaternions are wxyz; scales are stored as log, opacities as logit.

    `sh` is (N, K, 3) with K = (degree + 1)^2 coefficients per channel; `sh[:, 0]` is the DC term
    (colour = 0.5 + C0 * dc, C0 = 0.28209479177387814).
    """

    means: np.ndarray  # (N, 3)
    quats: np.ndarray  # (N, 4) wxyz
    log_scales: np.ndarray  # (N, 3)
    logit_opacities: np.ndarray  # (N,)
    sh: np.ndarray  # (N, K, 3)

    def __post_init__(self) -> None:
        self.means = np.ascontiguousarray(self.means, dtype=np.float32)
        self.quats = np.ascontiguousarray(self.quats, dtype=np.float32)
        self.log_scales = np.ascontiguousarray(self.log_scales, dtype=np.float32)
        self.logit_opacities = np.ascontiguousarray(self.logit_opacities, dtype=np.float32).reshape(-1)
        self.sh = np.ascontiguousarray(self.sh, dtype=np.float32)
        n = self.means.shape[0]
        expected = {
            "means": (self.means, (n, 3)),
            "quats": (self.quats, (n, 4)),
            "log_scales": (self.log_scales, (n, 3)),
            "logit_opacities": (self.logit_opacities, (n,)),
        }
        for name, (arr, shape) in expected.items():
            if arr.shape != shape:
                raise ValueError(f"GaussianCloud.{name}: expected shape {shape}, got {arr.shape}")
        if self.sh.ndim != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3:
            raise ValueError(f"GaussianCloud.sh: expected shape ({n}, K, 3), got {self.sh.shape}")
        if self.sh.shape[1] not in (1, 4, 9, 16):
            raise ValueError(f"GaussianCloud.sh: K must be 1, 4, 9 or 16 (SH degree 0..3), got {self.sh.shape[1]}")

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return int(round(np.sqrt(self.sh.shape[1]))) - 1
