"""`twinbench render-ply FILE --out image.png`: render a 3DGS file from an automatic framing viewpoint."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import tyro

from twinbench.errors import InputError


@dataclass(frozen=True)
class RenderPlyConfig:
    """Render a .ply / .splat / .spz Gaussian file to a PNG."""

    file: tyro.conf.Positional[Path]
    """Input Gaussian file (.ply, .splat or .spz)."""
    out: Path = Path("render.png")
    """Output PNG path."""
    width: int = 848
    """Image width in pixels."""
    height: int = 480
    """Image height in pixels."""
    fov_deg: float = 60.0
    """Horizontal field of view in degrees."""
    view_dir: tuple[float, float, float] = (0.0, -1.0, 0.6)
    """Direction from the cloud's centre towards the camera."""
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)
    """World direction shown as 'up' in the image (COLMAP/INRIA scans are often y-down: try 0 -1 0)."""
    percentile: float = 95.0
    """Frame the sphere holding this percentile of Gaussians (robust to stray floaters)."""
    background: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """Background RGB in [0, 1]."""
    device: str = "cpu"
    """Warp device: "cpu" or "cuda:N"."""


MAX_IMAGE_SIDE = 8192  # pixels; 8192 x 8192 float32 RGBA buffers are ~1 GiB


def check_config(config: RenderPlyConfig) -> None:
    """Refuse bad options before anything is loaded or allocated (InputError naming the option)."""
    for name in ("width", "height"):
        v = getattr(config, name)
        if not 1 <= v <= MAX_IMAGE_SIDE:
            raise InputError(f"--{name} {v}: must be between 1 and {MAX_IMAGE_SIDE} pixels")
    if not (np.isfinite(config.fov_deg) and 0 < config.fov_deg < 180):
        raise InputError(f"--fov-deg {config.fov_deg}: must be in (0, 180)")
    if not (np.isfinite(config.percentile) and 0 < config.percentile <= 100):
        raise InputError(f"--percentile {config.percentile}: must be in (0, 100]")
    for name in ("view_dir", "up"):
        v = np.asarray(getattr(config, name), dtype=np.float64)
        if not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-12:
            raise InputError(f"--{name.replace('_', '-')} {tuple(v)}: must be a finite non-zero direction")
    bg = np.asarray(config.background, dtype=np.float64)
    if not np.all((bg >= 0) & (bg <= 1)):
        raise InputError(f"--background {tuple(bg)}: each channel must be in [0, 1]")
    from twinbench.physics import check_device

    check_device(config.device, "--device")


def main(config: RenderPlyConfig) -> int:
    """Bad options or files raise InputError / GaussianFileError (one line via `twinbench`, exit code 2)."""
    import imageio.v3 as iio

    from twinbench.gaussians.camera import framing_camera
    from twinbench.gaussians.io import load_gaussians
    from twinbench.gaussians.render import render

    check_config(config)
    cloud = load_gaussians(config.file)
    cam = framing_camera(
        cloud,
        width=config.width,
        height=config.height,
        fov_deg=config.fov_deg,
        view_dir=config.view_dir,
        up=config.up,
        percentile=config.percentile,
    )
    out = render(cloud, cam, background=config.background, device=config.device)
    config.out.parent.mkdir(parents=True, exist_ok=True)
    iio.imwrite(config.out, out.rgb_uint8())
    print(f"wrote {config.out} ({config.width}x{config.height}, {len(cloud)} Gaussians)")
    return 0
