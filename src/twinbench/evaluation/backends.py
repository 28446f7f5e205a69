"""Where episode batches run: worker processes (`run_local`) or Ray (`run_ray`), each finished record
handed to `on_done` at once.

Worker processes (spawn context; `workers=0` runs the batches in the calling process) ignore SIGINT and
SIGTERM (the parent decides), exit as soon as their parent dies however it dies, and each runs one batch
at a time: a process that dies inside a batch (segfault, os._exit, OOM kill) has its episodes recorded
as sim_error with the reason, and a fresh process takes its place. `sigterm_as_interrupt` makes SIGTERM
take Ctrl-C's path in the parent (it raises `SigTerm`, a KeyboardInterrupt). A run on a thread other than
the main one, which no signal reaches, takes the same path when the event given to `stop_requests` is set.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading

from twinbench._runtime import quiet_warp, share_cores, watch_parent
from twinbench.errors import InputError
from twinbench.evaluation.rollout import EpisodeBatch, close_cached_policies, crash_record, run_batch
from twinbench.evaluation.video import error_text

RAY_HINT = "pip install 'twinbench[ray]'"


class SigTerm(KeyboardInterrupt):
    """Raised in the main thread by the SIGTERM handler, so SIGTERM takes Ctrl-C's path."""


class sigterm_as_interrupt:
    """Context manager: while active (main thread only), SIGTERM raises SigTerm."""

    def __enter__(self):
        import threading

        self._old = None
        if threading.current_thread() is threading.main_thread():
            def handler(signum, frame):
                raise SigTerm("SIGTERM")

            self._old = signal.signal(signal.SIGTERM, handler)
        return self

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGTERM, self._old)


_STOPS: dict[int, threading.Event] = {}  # thread id -> the event that stops its runs (stop_requests)
STOP_POLL_S = 0.2
"""how often a run under `stop_requests` looks at its event while its workers are busy"""


@contextlib.contextmanager
def stop_requests(event: threading.Event):
    """While active, the runs of this thread (`run_local`, `run_ray`) stop as after Ctrl-C once ``event``
    is set: a KeyboardInterrupt raised here, the finished episodes kept, the workers killed. For a run on a
    thread beside the main one, which a signal does not reach (`twinbench study run`'s real rollouts
    beside the reconstruction)."""
    key = threading.get_ident()
    _STOPS[key] = event
    try:
        yield event
    finally:
        _STOPS.pop(key, None)


def _stop_event() -> threading.Event | None:
    return _STOPS.get(threading.get_ident())


def _check_stop(event: threading.Event | None) -> None:
    if event is not None and event.is_set():
        raise KeyboardInterrupt("stop requested")


def refuse_in_worker_import(what: str) -> None:
    """Raise InputError when called while a worker process started with multiprocessing's "spawn" (the
    evaluation's workers) imports the parent's main script: a script that starts workers without an
    ``if __name__ == "__main__":`` guard runs its whole body again in every worker, which would redo (and
    write over) the parent's work instead of running episodes."""
    import multiprocessing as mp

    if getattr(mp.current_process(), "_inheriting", False):  # set by spawn while it imports __main__
        raise InputError(
            f"{what} was called while a worker process imports your script: worker processes (e.g. "
            "workers=2) import the main script again, so put the script's code under "
            "`if __name__ == \"__main__\":` (Python's multiprocessing rule for the spawn start method)")


def _exit_reason(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


def _worker_main(conn, cores: str = "1") -> None:
    """A worker process: says ("ready", None) once started, then runs one EpisodeBatch at a time from
    `conn`, replies ("ok", records) or ("error", exc).

    Ignores SIGINT and SIGTERM (the parent decides: commit finished episodes, kill the rest) and exits
    as soon as the parent dies."""
    import pickle

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    os.environ["TWINBENCH_CPU_THREADS"] = cores  # this worker's share of the cores (see share_cores)
    watch_parent()
    quiet_warp()  # workers print no Warp banner or module-load lines either
    try:
        conn.send(("ready", None))
        while True:
            try:
                job = conn.recv()
            except (EOFError, OSError):
                return
            if job is None:
                return
            try:
                reply = ("ok", run_batch(job))
            except BaseException as err:  # noqa: BLE001 - sent to the parent, which raises it
                try:
                    pickle.dumps(err)
                except Exception:  # noqa: BLE001
                    err = RuntimeError(error_text(err))
                reply = ("error", err)
            conn.send(reply)
    finally:
        close_cached_policies()


class _Worker:
    def __init__(self, ctx, cores: str):
        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=_worker_main, args=(child, cores), daemon=True,
                                   name="twinbench-worker")
        self.process.start()
        child.close()
        self.job: EpisodeBatch | None = None
        self.started = False  # said "ready": it got past importing the parent's script and twinbench

    def stop(self, graceful: bool) -> None:
        if graceful and self.job is None and self.process.is_alive():
            try:
                self.conn.send(None)
            except OSError:
                pass
            self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.kill()  # SIGKILL: workers ignore SIGTERM
            self.process.join(timeout=5)
        self.conn.close()


def _run_pool(jobs: list[EpisodeBatch], workers: int, on_done) -> None:
    """Run the batches `jobs` on `workers` spawned processes, one batch per process at a time, so that a
    process that dies (segfault, os._exit, OOM kill) is known to have died in its batch: its episodes are
    recorded as sim_error with the reason, a fresh process takes its place and the run goes on. An
    exception raised by run_batch itself (bad input) stops the run and is re-raised here."""
    import multiprocessing as mp
    from collections import deque
    from multiprocessing.connection import wait

    ctx = mp.get_context("spawn")
    cores = share_cores(workers)
    todo = deque(jobs)
    pool: list[_Worker] = []
    ok = False
    stop = _stop_event()
    try:
        while todo or any(w.job is not None for w in pool):
            _check_stop(stop)
            pool = [w for w in pool if w.job is not None or w.process.is_alive()]
            while todo and len(pool) < workers and sum(w.job is None for w in pool) < len(todo):
                pool.append(_Worker(ctx, cores))
            for w in pool:
                if w.job is None and todo:
                    w.job = todo.popleft()
                    w.conn.send(w.job)
            busy = [w for w in pool if w.job is not None]
            ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy],
                             timeout=None if stop is None else STOP_POLL_S))
            for w in pool:
                if w.job is None or not (w.conn in ready or w.process.sentinel in ready):
                    continue
                reply = None
                try:
                    if w.conn.poll():
                        reply = w.conn.recv()
                except (EOFError, OSError):
                    reply = None
                if reply is None:  # the process died inside the episode
                    w.process.join(timeout=5)
                    if not w.started and (w.process.exitcode or 0) > 0:  # an error before it could start
                        raise RuntimeError(
                            f"a worker process exited ({_exit_reason(w.process.exitcode)}) before it "
                            "started: its error is printed above. A script that runs episodes in worker "
                            "processes must keep its code under `if __name__ == \"__main__\":` (each "
                            "worker imports the script again)")
                    batch = w.job
                    w.job = None
                    w.stop(graceful=False)
                    for job in batch.jobs:
                        on_done(crash_record(job, f"worker process died during the episode "
                                                  f"({_exit_reason(w.process.exitcode)})"))
                    continue  # replaced at the top of the loop
                kind, value = reply
                if kind == "ready":
                    w.started = True
                    continue
                w.job = None
                if kind == "error":
                    raise value
                for rec in value:
                    on_done(rec)
        ok = True
    finally:
        for w in pool:
            w.stop(graceful=ok)


def run_local(batches: list[EpisodeBatch], workers: int, on_done) -> None:
    """Run `batches` in `workers` worker processes (0: in this process), `on_done(record)` for each."""
    if workers == 0:
        stop = _stop_event()
        try:
            for batch in batches:  # an episode here runs to its end: the event is looked at between batches
                _check_stop(stop)
                for rec in run_batch(batch):
                    on_done(rec)
        finally:
            close_cached_policies()
        return
    _run_pool(batches, workers, on_done)


def _import_ray():
    try:
        import ray
    except ImportError as err:
        raise ImportError(f"--backend ray needs the 'ray' extra ({RAY_HINT})") from err
    return ray


def run_ray(batches: list[EpisodeBatch], workers: int, on_done) -> None:
    """Run `batches` as Ray tasks (one CPU each), `on_done(record)` for each; a task whose worker died is
    recorded as sim_error."""
    ray = _import_ray()
    if not ray.is_initialized():
        ray.init(num_cpus=workers if workers > 0 else None, include_dashboard=False)
    # one CPU per task: a task's physics stays on one core (no split frames competing for cores)
    env_vars = {"TWINBENCH_CPU_THREADS": os.environ.get("TWINBENCH_CPU_THREADS", "1")}
    remote_batch = ray.remote(num_cpus=1, max_retries=0, runtime_env={"env_vars": env_vars})(run_batch)
    by_ref = {remote_batch.remote(batch): batch for batch in batches}
    pending = list(by_ref)
    stop = _stop_event()
    try:
        while pending:
            _check_stop(stop)
            done, pending = ray.wait(pending, num_returns=1, timeout=None if stop is None else STOP_POLL_S)
            if not done:
                continue
            try:
                recs = ray.get(done[0])
            except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError) as err:
                recs = [crash_record(job, f"the Ray worker died during the episode ({err})")
                        for job in by_ref[done[0]].jobs]
            for rec in recs:
                on_done(rec)
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise
