"""Evaluation runner overhead and remote-policy latency on the point-reach debug task.

Prints `name value unit` lines:
- runner throughput (episodes/s) in-process and with 2 spawn workers (process start-up included),
  for 64 expert episodes (12 steps each) with a 5 ms simulated step cost, and the ideal 2-worker figure;
- median websocket + msgpack round trip of one observation (two 64x64x3 images + state) to a local
  policy server.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from twinbench.evaluation.runner import evaluate
from twinbench.evaluation.store import ResultsStore
from twinbench.policies.remote import RemotePolicy
from twinbench.policies.server import PolicyServer
from twinbench.tasks import get_task
from twinbench.tasks.point_reach import PointReachExpert

N_EPISODES, STEP_DELAY = 64, 0.005


def main() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        store = ResultsStore(Path(tmp) / "bench.sqlite")
        for workers in (0, 2):
            t0 = time.perf_counter()
            evaluate("point-reach", ["expert"], N_EPISODES, workers, f"w{workers}", store, output_dir=tmp,
                     env_kwargs={"step_delay_s": STEP_DELAY})
            rate = N_EPISODES / (time.perf_counter() - t0)
            print(f"runner_point_reach_workers{workers} {rate:.1f} episodes/s")
        print(f"runner_point_reach_ideal_2workers {2 / (12 * STEP_DELAY):.1f} episodes/s")
    env = get_task("point-reach").make_env()
    obs, _ = env.reset(seed=0)
    with PolicyServer(PointReachExpert) as server:
        pol = RemotePolicy(server.url)
        pol.infer(obs)  # connect
        times = []
        for _ in range(300):
            t0 = time.perf_counter()
            pol.infer(obs)
            times.append(time.perf_counter() - t0)
        pol.close()
    print(f"remote_policy_roundtrip_median {1e3 * statistics.median(times):.3f} ms")
    print(f"remote_policy_roundtrip_p99 {1e3 * float(np.percentile(times, 99)):.3f} ms")


if __name__ == "__main__":
    main()
