"""Robot Gaussians: 3DGS splats stored in their link's frame and posed rigidly by forward kinematics."""

from __future__ import annotations

import numpy as np
import trimesh

from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.primitives import surface_discs
from twinbench.robot.model import RobotModel
from twinbench.transforms import matrix_to_quat, quat_multiply

# Colours for links whose URDF has no material (cycled).
_PALETTE = np.array(
    [
        [0.90, 0.90, 0.88],
        [0.75, 0.77, 0.80],
        [0.35, 0.35, 0.38],
        [0.80, 0.35, 0.20],
        [0.20, 0.35, 0.70],
        [0.30, 0.60, 0.30],
    ]
)


class RobotGaussians:
    """Gaussians attached to robot links. `local` holds means/quats in each Gaussian's link frame.

    Gaussians are kept sorted by link (stable), so `posed` transforms contiguous slices. The posed
    cloud shares `log_scales` / `logit_opacities` / DC colour arrays with this object (do not mutate);
    only the DC colour term is kept (higher SH bands are not rotated).
    """

    def __init__(self, model: RobotModel, local: GaussianCloud, link_index: np.ndarray):
        link_index = np.asarray(link_index, dtype=np.int64).reshape(-1)
        if link_index.shape[0] != len(local):
            raise ValueError(
                f"link_index: expected {len(local)} entries (one per Gaussian), got {link_index.shape[0]}"
            )
        if link_index.size and (link_index.min() < 0 or link_index.max() >= model.n_links):
            raise ValueError(
                f"link_index: values must be in [0, {model.n_links}) (model links), "
                f"got [{link_index.min()}, {link_index.max()}]"
            )
        order = np.argsort(link_index, kind="stable")
        self.model = model
        self.link_index = link_index[order]
        self.means = local.means[order]
        self.quats = local.quats[order]
        self.log_scales = np.ascontiguousarray(local.log_scales[order])
        self.logit_opacities = np.ascontiguousarray(local.logit_opacities[order])
        self.sh_dc = np.ascontiguousarray(local.sh[order][:, :1])
        bounds = np.searchsorted(self.link_index, np.arange(model.n_links + 1))
        self._slices = [
            (k, slice(bounds[k], bounds[k + 1])) for k in range(model.n_links) if bounds[k + 1] > bounds[k]
        ]

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def local(self) -> GaussianCloud:
        """The Gaussians in their link frames (sorted by link)."""
        return GaussianCloud(self.means, self.quats, self.log_scales, self.logit_opacities, self.sh_dc)

    @classmethod
    def from_world(
        cls, model: RobotModel, cloud: GaussianCloud, link_index: np.ndarray, q: np.ndarray | None = None
    ) -> RobotGaussians:
        """Attach world-frame Gaussians (e.g. a registered scan) seen at configuration q (default home)."""
        q = model.home_q if q is None else model.check_q(q)
        link_index = np.asarray(link_index, dtype=np.int64).reshape(-1)
        if link_index.shape[0] != len(cloud):
            raise ValueError(
                f"link_index: expected {len(cloud)} entries (one per Gaussian), got {link_index.shape[0]}"
            )
        t = model.fk(q)
        inv_r = np.swapaxes(t[:, :3, :3], -1, -2)[link_index]
        means = np.einsum("nij,nj->ni", inv_r, cloud.means - t[link_index, :3, 3])
        conj = matrix_to_quat(t[:, :3, :3]) * np.array([1.0, -1.0, -1.0, -1.0])
        quats = quat_multiply(conj[link_index], cloud.quats.astype(np.float64))
        local = GaussianCloud(means, quats, cloud.log_scales, cloud.logit_opacities, cloud.sh)
        return cls(model, local, link_index)

    def posed(self, q: np.ndarray) -> GaussianCloud:
        """World-frame Gaussians at configuration q: each moved rigidly by its link's FK pose."""
        t = self.model.fk(q)
        if t.ndim != 3:
            raise ValueError("q: posed() takes one configuration (n_q,), not a batch")
        rot = t[:, :3, :3].astype(np.float32)
        lq = matrix_to_quat(t[:, :3, :3]).astype(np.float32)
        trans = t[:, :3, 3].astype(np.float32)
        means = np.empty_like(self.means)
        quats = np.empty_like(self.quats)
        for k, s in self._slices:
            means[s] = self.means[s] @ rot[k].T + trans[k]
            quats[s] = quat_multiply(lq[k], self.quats[s])
        return GaussianCloud(means, quats, self.log_scales, self.logit_opacities, self.sh_dc)


def sample_robot_scan(
    model: RobotModel,
    *,
    spacing: float = 0.004,
    n_gaussians: int | None = None,
    link_colors: dict[str, np.ndarray] | None = None,
    opacity: float = 0.95,
    seed: int = 0,
) -> RobotGaussians:
    """Synthetic robot "scan": flat disc Gaussians sampled on each link's visual mesh, labelled by link.

    The number per link is area / spacing^2, or `n_gaussians` split by area when given (the disc size
    then follows the implied spacing). Discs lie in the surface (thin axis along the face normal) with
    radius ~ 0.7 spacing; colours come from `link_colors`, the URDF materials, or a palette.
    """
    links = [name for name in model.link_names if name in model.visual_meshes]
    if not links:
        raise ValueError(
            f"model {model.name!r} has no visual meshes to sample (was it loaded with load_meshes=False?)"
        )
    if not 0.0 < opacity < 1.0:
        raise ValueError(f"opacity: must be in (0, 1), got {opacity}")
    areas = np.array([model.visual_meshes[name].area for name in links])
    if n_gaussians is not None:
        if n_gaussians < len(links):
            raise ValueError(f"n_gaussians: need at least one per link ({len(links)}), got {n_gaussians}")
        spacing = float(np.sqrt(areas.sum() / n_gaussians))
        counts = np.maximum(1, np.floor(areas / areas.sum() * n_gaussians).astype(int))
        counts[np.argmax(areas)] += n_gaussians - counts.sum()
    else:
        if spacing <= 0:
            raise ValueError(f"spacing: must be > 0, got {spacing}")
        counts = np.maximum(1, np.round(areas / spacing**2).astype(int))
    rng = np.random.default_rng(seed)
    means, normals, idx, colors = [], [], [], []
    for k, (name, count) in enumerate(zip(links, counts, strict=True)):
        mesh: trimesh.Trimesh = model.visual_meshes[name]
        pts, faces = trimesh.sample.sample_surface(mesh, int(count), seed=rng)
        means.append(pts)
        normals.append(np.asarray(mesh.face_normals)[faces])
        idx.append(np.full(len(pts), model.link_index(name)))
        if link_colors is not None and name in link_colors:
            rgb = np.asarray(link_colors[name], dtype=np.float64)
        elif name in model.link_colors:
            rgb = model.link_colors[name]
        else:
            rgb = _PALETTE[k % len(_PALETTE)]
        colors.append(np.broadcast_to(rgb, (len(pts), 3)))
    cloud = surface_discs(
        np.concatenate(means), np.concatenate(normals), np.concatenate(colors), 0.7 * spacing, opacity=opacity
    )
    return RobotGaussians(model, cloud, np.concatenate(idx))
