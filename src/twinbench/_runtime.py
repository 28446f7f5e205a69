"""Process-level rules shared by commands, workers, helpers and plugins, written once: Warp's console
output, how many CPU cores the physics may use, and ending a child process when its parent dies."""

from __future__ import annotations

import os
import threading
import time

CPU_THREADS_ENV = "TWINBENCH_CPU_THREADS"


def quiet_warp() -> None:
    """Keep Warp's init banner and per-module load lines out of stdout (warnings still show).
    `TWINBENCH_WARP_VERBOSE=1` keeps them."""
    if os.environ.get("TWINBENCH_WARP_VERBOSE", "") not in ("", "0"):
        return
    import warp as wp

    wp.config.log_level = wp.LOG_WARNING


def cpu_cores() -> int:
    """CPU cores the physics and rendering may use: $TWINBENCH_CPU_THREADS, else the cores this process may
    run on."""
    env = os.environ.get(CPU_THREADS_ENV)
    if env:
        try:
            cores = int(env)
        except ValueError:
            raise ValueError(f"{CPU_THREADS_ENV}={env!r}: give a positive integer") from None
        return max(1, cores)
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def share_cores(workers: int) -> str:
    """$TWINBENCH_CPU_THREADS for each of `workers` processes: the cores shared out (a user's own setting
    wins), so that processes that split their frames over cores never oversubscribe the machine."""
    return os.environ.get(CPU_THREADS_ENV) or str(max(1, cpu_cores() // max(1, workers)))


def watch_parent(poll_s: float = 0.5, exit_code: int = 75) -> None:
    """Start a daemon thread that ends this process (`os._exit`) as soon as its parent dies, SIGKILL too.
    A multiprocessing child also waits on its parent's sentinel, so it notices at once."""
    import multiprocessing as mp
    from multiprocessing.connection import wait

    parent = mp.parent_process()
    sentinel = getattr(parent, "sentinel", None)
    ppid = os.getppid()

    def run() -> None:
        while True:
            if sentinel is not None:
                if wait([sentinel], timeout=poll_s):
                    os._exit(exit_code)
            else:
                time.sleep(poll_s)
            if os.getppid() != ppid:
                os._exit(exit_code)

    threading.Thread(target=run, name="twinbench-parent-watchdog", daemon=True).start()
