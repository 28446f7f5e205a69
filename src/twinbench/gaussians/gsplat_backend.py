"""The gsplat renderer backend ("gsplat": CUDA only, optional extra `gsplat`; Apache-licensed)."""

from __future__ import annotations

import numpy as np
import warp as wp

from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud
from twinbench.gaussians.render_rules import LOW_PASS, NEAR, TILE, RenderOutput
from twinbench.gaussians.sh import sh_degree


def gsplat_available() -> bool:
    try:
        import gsplat  # noqa: F401
        import torch  # noqa: F401
    except ImportError:
        return False
    return True


def _render_gsplat(cloud: GaussianCloud | DeviceGaussians, cams: list[Camera], background, device: str):
    try:
        import gsplat
        import torch
    except ImportError as exc:
        raise ImportError(
            "render(backend='gsplat') needs the optional extra: pip install twinbench[gsplat]"
        ) from exc
    if not device.startswith("cuda"):
        raise ValueError(
            f"render(backend='gsplat') runs on CUDA only, got device={device!r}; use backend='warp'"
        )
    dev = torch.device(device)
    if isinstance(cloud, DeviceGaussians):  # zero-copy views of the Warp arrays
        t = {
            "means": wp.to_torch(cloud.means),
            "quats": wp.to_torch(cloud.quats),
            "scales": wp.to_torch(cloud.scales),
            "opacities": wp.to_torch(cloud.opacities),
            "sh": wp.to_torch(cloud.sh),
        }
        degree = sh_degree(cloud.sh.shape[1])
    else:
        arrays = dict(
            means=cloud.means, quats=cloud.quats, scales=cloud.scales, opacities=cloud.opacities, sh=cloud.sh
        )
        t = {k: torch.as_tensor(v, device=dev) for k, v in arrays.items()}
        degree = cloud.sh_degree
    outputs: list[RenderOutput | None] = [None] * len(cams)
    groups: dict[tuple[int, int], list[int]] = {}
    for i, cam in enumerate(cams):
        groups.setdefault((cam.width, cam.height), []).append(i)
    for (w, h), idx in groups.items():
        viewmats = torch.as_tensor(
            np.stack([cams[i].world_to_cam for i in idx]), dtype=torch.float32, device=dev
        )
        ks = torch.as_tensor(np.stack([cams[i].K for i in idx]), dtype=torch.float32, device=dev)
        colors, alphas, _ = gsplat.rasterization(
            t["means"],
            t["quats"],
            t["scales"],
            t["opacities"],
            t["sh"],
            viewmats,
            ks,
            w,
            h,
            near_plane=NEAR,
            eps2d=LOW_PASS,
            sh_degree=degree,
            tile_size=TILE,
            render_mode="RGB+ED",
        )
        # the background composited here (colour + transmittance * background, as gsplat would): gsplat
        # 1.5's packed mode refuses its own `backgrounds` argument once it appends the depth channel
        colors = colors.detach().cpu().numpy()
        alphas = alphas.detach().cpu().numpy()
        bg = np.asarray(background, dtype=np.float32)
        for j, i in enumerate(idx):
            a = alphas[j, :, :, 0]
            outputs[i] = RenderOutput(
                rgb=np.clip(colors[j, :, :, :3] + (1.0 - a)[..., None] * bg, 0, 1).astype(np.float32),
                depth=np.where(a > 0, colors[j, :, :, 3], 0).astype(np.float32),
                alpha=a.astype(np.float32),
            )
    return outputs  # type: ignore[return-value]


def render_views(views: list[tuple[GaussianCloud | DeviceGaussians, Camera]], background: np.ndarray,
                 device: str, threads: int) -> list[RenderOutput]:
    """The "gsplat" backend (see render.render_batch): the views of one cloud in one gsplat call."""
    clouds: dict[int, tuple[GaussianCloud | DeviceGaussians, list[int]]] = {}
    for i, (cloud, _) in enumerate(views):
        clouds.setdefault(id(cloud), (cloud, []))[1].append(i)
    outs: list = [None] * len(views)
    for cloud, idx in clouds.values():
        if isinstance(cloud, DeviceGaussians) and str(cloud.device) != str(device):
            raise ValueError(f"render: DeviceGaussians live on {cloud.device}, but device={device!r}")
        done = _render_gsplat(cloud, [views[i][1] for i in idx], background, device)
        for i, out in zip(idx, done, strict=True):
            outs[i] = out
    return outs
