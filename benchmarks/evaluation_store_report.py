"""Results store write speed (1 and 4 processes), MMRV bootstrap and HTML report generation time.

Prints `name value unit` lines (medians of repeated runs where repeated).
"""

from __future__ import annotations

import multiprocessing as mp
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from twinbench.evaluation.metrics import mmrv_bootstrap
from twinbench.evaluation.report import VideoLimits, write_report
from twinbench.evaluation.store import EpisodeRecord, ResultsStore


def _rec(run: str, policy: str, i: int, domain: str = "sim", ok: bool = True) -> EpisodeRecord:
    return EpisodeRecord(run, "push-t", policy, "step_1", 1, i, 0, domain, ok, "ok", steps=1800,
                         wall_time_s=3.0, metrics={"sum_reward": 1.5})


def _writer(path: str, worker: int, n: int) -> None:
    store = ResultsStore(path)
    for i in range(n):
        store.record_episode(_rec("bench", f"p{worker}", i))


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        store = ResultsStore(Path(tmp) / "one.sqlite")
        times = []
        for i in range(300):
            t0 = time.perf_counter()
            store.record_episode(_rec("bench", "p", i))
            times.append(time.perf_counter() - t0)
        print(f"store_record_episode_1proc {1e3 * statistics.median(times):.2f} ms")

        path = str(Path(tmp) / "four.sqlite")
        ResultsStore(path)
        n = 200
        ctx = mp.get_context("spawn")
        procs = [ctx.Process(target=_writer, args=(path, w, n)) for w in range(4)]
        t0 = time.perf_counter()
        for p in procs:
            p.start()
        for p in procs:
            p.join()
        dt = time.perf_counter() - t0  # includes interpreter start-up of the 4 processes
        assert len(ResultsStore(path).episodes()) == 4 * n
        print(f"store_4proc_throughput_incl_startup {4 * n / dt:.0f} episodes/s")

    rng = np.random.default_rng(0)
    sim = [rng.random(50) < p for p in np.linspace(0.1, 0.9, 10)]
    real = [rng.random(20) < p for p in np.linspace(0.15, 0.85, 10)]
    times = []
    for _ in range(5):
        t0 = time.perf_counter()
        mmrv_bootstrap(sim=sim, real=real, n_boot=2000, seed=0)
        times.append(time.perf_counter() - t0)
    print(f"mmrv_bootstrap_10pol_2000 {1e3 * statistics.median(times):.1f} ms")

    with tempfile.TemporaryDirectory() as tmp:
        store = ResultsStore(Path(tmp) / "r.sqlite")
        store.start_run("bench", "push-t", {"task": "push-t"})
        recs = []
        for k, p in enumerate(np.linspace(0.1, 0.9, 8)):
            recs += [_rec("bench", f"policy{k}", i, ok=bool(rng.random() < p)) for i in range(200)]
            recs += [_rec("real", f"policy{k}", i, "real", ok=bool(rng.random() < p)) for i in range(20)]
        store.record_episodes(recs)
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            write_report(store, "bench", Path(tmp) / "r.html", real_run_id="real", videos=VideoLimits(0))
            times.append(time.perf_counter() - t0)
        print(f"report_8pol_1760ep_no_video {statistics.median(times):.2f} s")


if __name__ == "__main__":
    main()
