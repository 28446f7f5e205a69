"""3DGS rendering: `render` / `render_batch` and the registry of renderer backends.

Backends (all follow render_rules: DESIGN §6): "warp", the Warp tile rasteriser on CPU or CUDA
(warp_raster); "gsplat", CUDA only, optional extra `gsplat` (gsplat_backend); "reference", the brute-force
NumPy renderer the others are tested against (reference). "auto" is gsplat on CUDA when installed, else
warp. A backend is a function ``fn(views, background, device, threads) -> list[RenderOutput]``
(`register_backend`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from twinbench.errors import InputError
from twinbench.gaussians import gsplat_backend, reference, warp_raster
from twinbench.gaussians.camera import Camera
from twinbench.gaussians.cloud import DeviceGaussians, GaussianCloud, SplitGaussians
from twinbench.gaussians.gsplat_backend import gsplat_available
from twinbench.gaussians.render_rules import RenderOutput
from twinbench.gaussians.threads import default_threads
from twinbench.gaussians.warp_raster import RenderCache

Backend = Callable[[list, np.ndarray, str, int], list[RenderOutput]]
_BACKENDS: dict[str, Backend] = {}


def register_backend(name: str, fn: Backend) -> None:
    """Make `fn` available as ``render(..., backend=name)``: it gets the (cloud, Camera) views, the
    background (3 float32), the device ("cpu", "cuda:0", ...) and the CPU thread count, and returns one
    RenderOutput per view, in order. A name registered again is replaced."""
    if not name or name == "auto":
        raise InputError(f"register_backend: {name!r} cannot name a backend")
    _BACKENDS[name] = fn


def backends() -> list[str]:
    """The registered backends' names."""
    return list(_BACKENDS)


register_backend("warp", warp_raster.render_views)
register_backend("gsplat", gsplat_backend.render_views)
register_backend("reference", reference.render_views)


def render(
    cloud: GaussianCloud | DeviceGaussians,
    cameras: Camera | Sequence[Camera],
    *,
    background=(0.0, 0.0, 0.0),
    backend: str = "auto",
    device: str | None = None,
    threads: int | None = None,
) -> RenderOutput | list[RenderOutput]:
    """Render `cloud` from one camera (returns a RenderOutput) or a list (returns a list).

    backend: "warp" (CPU or CUDA), "gsplat" (CUDA, extra `gsplat`), "reference" (NumPy, slow), another
    registered one (`backends()`), or "auto" (gsplat on CUDA when installed, else warp). device defaults
    to the DeviceGaussians' device, else "cpu". On CPU, work is split over `threads` Python threads
    (default: the cores this process may use, $TWINBENCH_CPU_THREADS if set, at most 8; Warp kernels
    release the GIL): cameras across threads when there are several, else Gaussians and tiles.
    """
    single = isinstance(cameras, Camera)
    cams = [cameras] if single else list(cameras)
    if not cams:
        raise ValueError("render: `cameras` is empty")
    outs = render_batch(
        [(cloud, c) for c in cams], background=background, backend=backend, device=device, threads=threads
    )
    return outs[0] if single else outs


def render_batch(
    views: Sequence[tuple[GaussianCloud | DeviceGaussians | SplitGaussians, Camera]],
    *,
    background=(0.0, 0.0, 0.0),
    backend: str = "auto",
    device: str | None = None,
    threads: int | None = None,
    cache: RenderCache | None = None,
) -> list[RenderOutput]:
    """Render many (cloud, camera) views in one call, e.g. every camera of every world of a many-world
    twin -> one RenderOutput per view, in order. Arguments as `render`. On CUDA (Warp) every stage runs
    once for all views; on CPU the views are dealt to the threads, and one view alone is split over the
    threads by Gaussians and tile rows instead (see warp_raster.render_views). Each view's pixels are the
    same as rendering it alone.

    A view's cloud may be a SplitGaussians(static, moving) (rendered as [static | moving]); with a `cache`
    (RenderCache) and the "warp" backend, the static part's work for a camera that has not moved is kept
    between calls and only the moving part is projected (images unchanged, bit for bit). Other backends
    render the concatenation."""
    views = list(views)
    if not views:
        raise ValueError("render: no views to render")
    for _, c in views:
        if not isinstance(c, Camera):
            raise ValueError(f"render: cameras must be Camera objects, got {type(c).__name__}")
    bg = np.asarray(background, dtype=np.float32).reshape(-1)
    if bg.shape != (3,):
        raise ValueError(f"render: background must be 3 floats, got {background!r}")
    if backend != "auto" and backend not in _BACKENDS:
        raise InputError(f"render: unknown backend {backend!r}; known: 'auto', "
                         + ", ".join(repr(b) for b in _BACKENDS))
    first = views[0][0]
    if device is None:
        device = str(first.device) if isinstance(first, DeviceGaussians | SplitGaussians) else "cpu"
    if backend == "auto":
        backend = "gsplat" if (device.startswith("cuda") and gsplat_available()) else "warp"
    threads = default_threads() if threads is None else max(1, int(threads))
    fn = _BACKENDS[backend]
    if fn is warp_raster.render_views:
        return fn(views, bg, device, threads, cache=cache)
    merged: dict[int, DeviceGaussians] = {}
    for cloud, _ in views:
        if isinstance(cloud, SplitGaussians) and id(cloud) not in merged:
            merged[id(cloud)] = cloud.merged()
    return fn([(merged.get(id(cloud), cloud), cam) for cloud, cam in views], bg, device, threads)


__all__ = [
    "RenderCache",
    "RenderOutput",
    "SplitGaussians",
    "backends",
    "gsplat_available",
    "register_backend",
    "render",
    "render_batch",
]
