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
    if parts == 1:
        if dim > 0:
            wp.launch(kernel, dim=dim, inputs=inputs + [int(start)], outputs=outputs, device=device)
        return
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


class WorkBoard:
    """Work of several owners shared with threads that have none of their own left: an owner `share`s a
    list of tasks (callables) and runs them itself, taking the next one each time, while threads done
    with their own work take them too (`help` until every owner has `finish`ed). Each task runs once;
    `share` returns when all of its tasks have run and re-raises the first error one raised."""

    def __init__(self, owners: int) -> None:
        self.owners = int(owners)
        self._cond = threading.Condition()
        self._open = int(owners)  # owners that may still share work
        self._queues: list[_Shared] = []

    def share(self, tasks: list) -> None:
        shared = _Shared(tasks)
        with self._cond:
            self._queues.append(shared)
            self._cond.notify_all()
        while (task := self._take(shared)) is not None:
            self._run(shared, task)
        with self._cond:
            while shared.running:
                self._cond.wait()
            self._queues.remove(shared)
        if shared.error is not None:
            raise shared.error

    def finish(self) -> None:
        """An owner has no more work to share (call it once per owner, also after an error)."""
        with self._cond:
            self._open -= 1
            self._cond.notify_all()

    def help(self) -> None:
        """Run other owners' shared tasks until every owner has finished."""
        while True:
            with self._cond:
                while True:
                    found = next(((q, q.tasks.pop()) for q in self._queues if q.tasks), None)
                    if found is not None or self._open <= 0:
                        break
                    self._cond.wait()
                if found is None:
                    return
                found[0].running += 1
            self._run(*found)

    def _take(self, shared: _Shared):
        with self._cond:
            if not shared.tasks:
                return None
            shared.running += 1
            return shared.tasks.pop()

    def _run(self, shared: _Shared, task) -> None:
        try:
            task()
        except BaseException as exc:  # noqa: BLE001 - re-raised by the task's owner
            shared.error = shared.error or exc
        finally:
            with self._cond:
                shared.running -= 1
                self._cond.notify_all()


class _Shared:
    def __init__(self, tasks: list) -> None:
        self.tasks = list(reversed(tasks))  # popped from the end: in the given order
        self.running = 0
        self.error: BaseException | None = None
