"""The CPU threads of rendering and posing: one pool, started once (a thread start costs ~0.1 ms), and
Warp kernels split over it (Warp releases the GIL while a CPU kernel runs)."""

from __future__ import annotations

import os
import threading
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import warp as wp

from twinbench._runtime import cpu_cores

_POOL_LOCK = threading.Lock()
_POOL: ThreadPoolExecutor | None = None
_IN_POOL = threading.local()


def default_threads() -> int:
    """Threads a render or a pose uses unless told: the cores this process may use (`cpu_cores`:
    $TWINBENCH_CPU_THREADS, e.g. an evaluation worker's share), at most 8."""
    return max(1, min(8, cpu_cores()))


def _pool_thread_init() -> None:
    _IN_POOL.active = True


def _forget_pool() -> None:
    """In a forked child: the parent's pool threads do not exist there (a task sent to them would never
    run), and its lock may have been held at the fork; start afresh."""
    global _POOL, _POOL_LOCK
    _POOL_LOCK = threading.Lock()
    _POOL = None


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_pool)


def run_threads(fns) -> None:
    """Call each function, the first in this thread and the others in the pool's threads (in turn, in
    this thread, when called from one of them: no task waits on a queued task); re-raise the first
    error."""
    if not fns:
        return
    if len(fns) == 1 or getattr(_IN_POOL, "active", False):
        for fn in fns:
            fn()
        return
    global _POOL
    with _POOL_LOCK:
        if _POOL is None:
            _POOL = ThreadPoolExecutor(8, "twinbench-render", initializer=_pool_thread_init)
        pool = _POOL
    futures = [pool.submit(fn) for fn in fns[1:]]
    error: BaseException | None = None
    try:
        fns[0]()
    except BaseException as exc:  # re-raised once the workers are done with the shared buffers
        error = exc
    for fut in futures:
        exc = fut.exception()
        error = error or exc
    if error is not None:
        raise error


def launch_split(kernel, dim: int, inputs: list, outputs: list, device, threads: int, start: int = 0):
    """Launch `kernel` over [start, start + dim) in `threads` contiguous chunks (its last input is the
    chunk start); on CPU each chunk runs in its own thread, on other devices it is one launch."""
    parts = threads if (device.is_cpu and threads > 1) else 1
    cut = np.linspace(start, start + dim, parts + 1).astype(int)
    run_threads(
        [
            (
                lambda lo=lo, hi=hi: wp.launch(
                    kernel, dim=hi - lo, inputs=inputs + [int(lo)], outputs=outputs, device=device
                )
            )
            for lo, hi in zip(cut[:-1], cut[1:], strict=True)
            if hi > lo
        ]
    )
