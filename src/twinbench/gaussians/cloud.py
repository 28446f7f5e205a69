"""GaussianCloud: the 3D Gaussian Splatting data object (host arrays, float32)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from twinbench.gaussians.sh import rotate_sh, sh_degree
from twinbench.transforms import matrix_to_quat, quat_multiply

if TYPE_CHECKING:
    import warp as wp


SH_C0 = 0.28209479177387814


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
            raise ValueError(
                f"GaussianCloud.sh: K must be 1, 4, 9 or 16 (SH degree 0..3), got {self.sh.shape[1]}"
            )

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return sh_degree(self.sh.shape[1])

    # ----- derived quantities -------------------------------------------------------------------
    @property
    def scales(self) -> np.ndarray:
        """Linear scales (N, 3)."""
        return np.exp(self.log_scales)

    @property
    def opacities(self) -> np.ndarray:
        """Opacities in (0, 1) (N,)."""
        return (1.0 / (1.0 + np.exp(-self.logit_opacities.astype(np.float64)))).astype(np.float32)

    @property
    def base_colours(self) -> np.ndarray:
        """View-independent colour 0.5 + C0 * DC (N, 3), not clamped."""
        return 0.5 + SH_C0 * self.sh[:, 0]

    def copy(self) -> GaussianCloud:
        return GaussianCloud(
            self.means.copy(),
            self.quats.copy(),
            self.log_scales.copy(),
            self.logit_opacities.copy(),
            self.sh.copy(),
        )

    # ----- selection ----------------------------------------------------------------------------
    @staticmethod
    def concatenate(clouds: Sequence[GaussianCloud]) -> GaussianCloud:
        """One cloud holding all Gaussians of `clouds` in order; lower SH degrees are zero-padded."""
        clouds = list(clouds)
        if not clouds:
            raise ValueError("GaussianCloud.concatenate: `clouds` is empty; pass at least one cloud")
        k = max(c.sh.shape[1] for c in clouds)
        sh = [np.pad(c.sh, ((0, 0), (0, k - c.sh.shape[1]), (0, 0))) for c in clouds]
        return GaussianCloud(
            np.concatenate([c.means for c in clouds]),
            np.concatenate([c.quats for c in clouds]),
            np.concatenate([c.log_scales for c in clouds]),
            np.concatenate([c.logit_opacities for c in clouds]),
            np.concatenate(sh),
        )

    def spatially_sorted(self) -> GaussianCloud:
        """The same Gaussians in Morton (z-order) order of their means on a 1024^3 grid over their bounding
        box, ties in index order: neighbours in space become neighbours in the arrays, so a renderer can
        cull runs of them at once (the warp backend's projection does, for the static part of a
        SplitGaussians kept in a RenderCache)."""
        if len(self) == 0:
            return self
        lo, hi = self.means.min(axis=0), self.means.max(axis=0)
        cell = np.clip((self.means - lo) / np.maximum(hi - lo, 1e-12) * 1024, 0, 1023).astype(np.uint64)
        code = np.zeros(len(self), dtype=np.uint64)
        for bit in range(10):
            for axis in range(3):
                code |= ((cell[:, axis] >> np.uint64(bit)) & np.uint64(1)) << np.uint64(3 * bit + axis)
        return self.subset(np.argsort(code, kind="stable"))

    def subset(self, index: np.ndarray | slice | Sequence[int]) -> GaussianCloud:
        """Gaussians selected by an integer index array, a slice or a boolean mask of length N."""
        if isinstance(index, slice):
            idx = index
        else:
            idx = np.asarray(index)
            if idx.size == 0 and idx.dtype != bool:
                idx = idx.astype(np.int64)
            if idx.dtype == bool and idx.shape != (len(self),):
                raise ValueError(
                    f"GaussianCloud.subset: boolean mask has shape {idx.shape}, expected ({len(self)},)"
                )
            if idx.dtype != bool and idx.size and not np.issubdtype(idx.dtype, np.integer):
                raise ValueError(
                    f"GaussianCloud.subset: index must be integers or a boolean mask, got {idx.dtype}"
                )
        return GaussianCloud(
            self.means[idx], self.quats[idx], self.log_scales[idx], self.logit_opacities[idx], self.sh[idx]
        )

    def box_mask(self, center, rotation, half_extents) -> np.ndarray:
        """Boolean (N,) mask of means inside the oriented box (centre (3,), box-to-world rotation (3,3),
        half extents (3,))."""
        center = np.asarray(center, dtype=np.float64).reshape(3)
        rot = np.asarray(rotation, dtype=np.float64).reshape(3, 3)
        half = np.asarray(half_extents, dtype=np.float64).reshape(3)
        if np.any(half < 0):
            raise ValueError(f"crop box: half_extents must be >= 0, got {half}")
        local = (self.means - center) @ rot  # rows: R^T (p - c)
        return np.all(np.abs(local) <= half, axis=1)

    def crop(self, center, rotation, half_extents, *, invert: bool = False) -> GaussianCloud:
        """Gaussians whose mean lies inside (or, with invert=True, outside) an oriented box."""
        mask = self.box_mask(center, rotation, half_extents)
        return self.subset(~mask if invert else mask)

    def downsample(self, max_gaussians: int) -> GaussianCloud:
        """Keep at most `max_gaussians`: the ones with the largest opacity * ellipsoid volume
        (sigmoid(logit) * sx*sy*sz), which drops the faint and tiny ones first; order is preserved."""
        if max_gaussians < 0:
            raise ValueError(f"downsample: max_gaussians must be >= 0, got {max_gaussians}")
        if len(self) <= max_gaussians:
            return self.copy()
        score = self.logit_opacities.astype(np.float64)
        # log(sigmoid(o)) + sum(log s): monotone in opacity * volume, no overflow
        score = -np.logaddexp(0.0, -score) + self.log_scales.astype(np.float64).sum(axis=1)
        keep = np.sort(np.argpartition(-score, max_gaussians - 1)[:max_gaussians]) if max_gaussians else []
        return self.subset(np.asarray(keep, dtype=np.int64))

    # ----- transforms ---------------------------------------------------------------------------
    def transform(self, matrix, *, sh_mode: str = "rotate") -> GaussianCloud:
        """Apply a 4x4 similarity transform (rotation, translation, optional uniform scale).

        Means are mapped, quaternions pre-multiplied by the rotation, log scales shifted by log(scale).
        sh_mode "rotate" rotates the view-dependent SH bands (exact, per-band matrices); "dc_only"
        leaves them unchanged (correct only for degree 0 or view-independent clouds).
        """
        if sh_mode not in ("rotate", "dc_only"):
            raise ValueError(f"transform: sh_mode must be 'rotate' or 'dc_only', got {sh_mode!r}")
        m = np.asarray(matrix, dtype=np.float64)
        if m.shape != (4, 4) or not np.all(np.isfinite(m)):
            raise ValueError(f"transform: matrix must be a finite 4x4 array, got shape {m.shape}")
        a = m[:3, :3]
        scale = np.cbrt(np.linalg.det(a))
        if scale <= 0:
            raise ValueError("transform: matrix has a reflection or is singular (det <= 0)")
        rot = a / scale
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-5):
            raise ValueError("transform: the 3x3 block must be a rotation times a uniform scale")
        means = self.means @ a.T + m[:3, 3]
        quats = quat_multiply(matrix_to_quat(rot)[None, :], self.quats)
        sh = rotate_sh(self.sh, rot) if (sh_mode == "rotate" and self.sh_degree > 0) else self.sh.copy()
        return GaussianCloud(
            means, quats, self.log_scales + np.float32(np.log(scale)), self.logit_opacities.copy(), sh
        )

    # ----- device arrays ------------------------------------------------------------------------
    def to_device(self, device: str = "cpu") -> DeviceGaussians:
        """Warp arrays on `device` for rendering / skinning (normalised quats, linear scales, opacities)."""
        return DeviceGaussians.from_cloud(self, device)


@dataclass
class DeviceGaussians:
    """Render-ready Warp arrays: means vec3, quats vec4 (wxyz, normalised), scales vec3 (linear),
    opacities float32 (0..1), sh array2d(vec3) (N, K)."""

    means: wp.array
    quats: wp.array
    scales: wp.array
    opacities: wp.array
    sh: wp.array
    # set by `segment`: (the cloud whose arrays these views are part of, index of the first Gaussian there)
    base: tuple[DeviceGaussians, int] | None = field(default=None, repr=False, compare=False)

    @property
    def device(self):
        return self.means.device

    def segment(self, start: int, count: int) -> DeviceGaussians:
        """Gaussians [start, start + count) as views of this cloud's arrays (writes to them land here). A
        batch render of segments of one cloud reads that cloud in place instead of concatenating."""
        if start < 0 or count < 0 or start + count > len(self):
            raise ValueError(
                f"segment [{start}, {start + count}) is outside the cloud's {len(self)} Gaussians"
            )
        end = start + count
        root, offset = self.parent()
        return DeviceGaussians(self.means[start:end], self.quats[start:end], self.scales[start:end],
                               self.opacities[start:end], self.sh[start:end], base=(root, offset + start))

    def parent(self) -> tuple[DeviceGaussians, int]:
        """(cloud, index of this cloud's first Gaussian there) for a `segment`, else (self, 0). Checked
        against the arrays' addresses, so a segment whose arrays were swapped since counts as its own."""
        if self.base is None:
            return self, 0
        root, start = self.base
        for name in ("means", "quats", "scales", "opacities", "sh"):
            mine, theirs = getattr(self, name), getattr(root, name)
            if mine.ptr != theirs.ptr + start * theirs.strides[0] or mine.shape[1:] != theirs.shape[1:]:
                return self, 0
        return root, start

    def __len__(self) -> int:
        return self.means.shape[0]

    def with_pose(self, means: wp.array, quats: wp.array) -> DeviceGaussians:
        """Same Gaussians with new means (vec3) and unit quats (vec4 wxyz), e.g. an LBSSkinner's output."""
        if means.shape[0] != len(self) or quats.shape[0] != len(self):
            raise ValueError(
                f"with_pose: expected {len(self)} means and quats, got {means.shape[0]} and {quats.shape[0]}"
            )
        return DeviceGaussians(means, quats, self.scales, self.opacities, self.sh)

    @staticmethod
    def concatenate(items: Sequence[DeviceGaussians]) -> DeviceGaussians:
        """One device cloud holding `items` in order (device-to-device copies; the SH of lower degree
        are zero-padded through the host)."""
        import warp as wp

        items = list(items)
        if not items:
            raise ValueError("DeviceGaussians.concatenate: `items` is empty")
        device = items[0].device
        if any(it.device != device for it in items):
            raise ValueError("DeviceGaussians.concatenate: all items must live on the same device")
        n = sum(len(it) for it in items)
        k = max(it.sh.shape[1] for it in items)
        out = DeviceGaussians(
            means=wp.empty(n, dtype=wp.vec3, device=device),
            quats=wp.empty(n, dtype=wp.vec4, device=device),
            scales=wp.empty(n, dtype=wp.vec3, device=device),
            opacities=wp.empty(n, dtype=wp.float32, device=device),
            sh=wp.zeros((n, k), dtype=wp.vec3, device=device),
        )
        start = 0
        for it in items:
            m = len(it)
            for name in ("means", "quats", "scales", "opacities"):
                wp.copy(getattr(out, name), getattr(it, name), dest_offset=start, count=m)
            if it.sh.shape[1] == k:
                wp.copy(out.sh, it.sh, dest_offset=start * k, count=m * k)
            else:
                sh = np.zeros((m, k, 3), np.float32)
                sh[:, : it.sh.shape[1]] = it.sh.numpy()
                wp.copy(
                    out.sh, wp.array(sh, dtype=wp.vec3, device=device), dest_offset=start * k, count=m * k
                )
            start += m
        return out

    @staticmethod
    def from_cloud(cloud: GaussianCloud, device: str = "cpu") -> DeviceGaussians:
        import warp as wp

        q = cloud.quats.astype(np.float64)
        norm = np.linalg.norm(q, axis=1, keepdims=True)
        q = np.where(norm > 0, q / np.maximum(norm, 1e-30), np.array([1.0, 0, 0, 0]))
        return DeviceGaussians(
            means=wp.array(cloud.means, dtype=wp.vec3, device=device),
            quats=wp.array(q.astype(np.float32), dtype=wp.vec4, device=device),
            scales=wp.array(cloud.scales, dtype=wp.vec3, device=device),
            opacities=wp.array(cloud.opacities, dtype=wp.float32, device=device),
            sh=wp.array(cloud.sh, dtype=wp.vec3, device=device),
        )


@dataclass
class SplitGaussians:
    """A cloud in two parts, rendered as their concatenation [static | moving]: `static` stays put between
    renders (a warp RenderCache keeps its per-camera work), `moving` may change every render. Many clouds
    may share one `static` (e.g. a twin's worlds). `whole`, when the caller has it, is the same Gaussians
    in one cloud (full renders and other backends read it instead of a concatenated copy)."""

    static: DeviceGaussians
    moving: DeviceGaussians
    whole: DeviceGaussians | None = field(default=None, repr=False, compare=False)

    def __post_init__(self) -> None:
        if self.static.device != self.moving.device:
            raise ValueError("SplitGaussians: static and moving must live on the same device")
        if self.whole is not None and len(self.whole) != len(self):
            raise ValueError(f"SplitGaussians: whole has {len(self.whole)} Gaussians, not {len(self)}")

    @property
    def device(self):
        return self.static.device

    def __len__(self) -> int:
        return len(self.static) + len(self.moving)

    def merged(self) -> DeviceGaussians:
        """One device cloud [static | moving]: `whole`, else a concatenated copy."""
        if self.whole is not None:
            return self.whole
        return DeviceGaussians.concatenate([self.static, self.moving])
