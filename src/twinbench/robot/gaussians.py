"""Robot Gaussians: 3DGS splats stored in their link's frame and posed rigidly by forward kinematics."""

from __future__ import annotations

import numpy as np
import trimesh

from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud
from twinbench.gaussians.primitives import surface_discs
from twinbench.gaussians.skinning import LabelRigidPoser
from twinbench.robot.model import RobotModel
from twinbench.transforms import invert_pose

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
    """Gaussians attached to robot links. `local` holds them in each Gaussian's link frame.

    Posing moves every Gaussian rigidly with its link's FK pose (positions, rotations and the SH bands),
    through `gaussians.skinning.LabelRigidPoser`: `posed(q)` on the host, `device_poser(...)` for a
    scene's device buffer. Gaussians are kept sorted by link (stable).
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
        self.log_scales = local.log_scales[order]  # fancy indexing: fresh C-contiguous copies
        self.logit_opacities = local.logit_opacities[order]
        self.sh = local.sh[order]
        self._host_poser = None

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def local(self) -> GaussianCloud:
        """The Gaussians in their link frames (sorted by link)."""
        return GaussianCloud(self.means, self.quats, self.log_scales, self.logit_opacities, self.sh)

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
        # Into the link frames: the inverse of posing (SH bands rotated too).
        g = LabelRigidPoser(cloud, link_index, model.n_links).update(invert_pose(model.fk(q)))
        return cls(model, _host_cloud(g, cloud), link_index)

    def device_poser(self, device: str = "cpu", out: DeviceGaussians | None = None,
                     first: int = 0) -> LabelRigidPoser:
        """A poser of these Gaussians from index `first` on (e.g. past those on links that never move) on
        `device`; `poser.update(model.fk(q))` poses them (into `out`)."""
        part = self.local if first == 0 else self.local.subset(slice(first, len(self)))
        return LabelRigidPoser(part, self.link_index[first:], self.model.n_links, device, out=out)

    def posed(self, q: np.ndarray) -> GaussianCloud:
        """World-frame Gaussians at configuration q: each moved rigidly by its link's FK pose."""
        t = self.model.fk(q)
        if t.ndim != 3:
            raise ValueError("q: posed() takes one configuration (n_q,), not a batch")
        if self._host_poser is None:
            self._host_poser = self.device_poser("cpu")
        return _host_cloud(self._host_poser.update(t), self.local)


def _host_cloud(posed: DeviceGaussians, rest: GaussianCloud) -> GaussianCloud:
    """Host copy of posed means, quats and SH, with the rest cloud's (pose-invariant) scales, opacities.
    (On CPU `wp.array.numpy()` is a view of the poser's buffer, which the next update overwrites.)"""
    return GaussianCloud(
        posed.means.numpy().copy(), posed.quats.numpy().copy(), rest.log_scales, rest.logit_opacities,
        posed.sh.numpy().copy(),
    )


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
