"""Wall time per stage of `twinbench study run --size small` (issue #24: under 60 min per task on 2 cores).

Runs the study (or reads DIR/study.json of one already run with --read) and prints `stage seconds` lines,
each evaluation's time, the table, and the machine's core count.

Usage: python benchmarks/study.py [--task push-t] [--out /tmp/study_pusht] [--size small] [--workers 2]
                                  [--device cpu|cuda]
       python benchmarks/study.py --read /tmp/study_pusht
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--task", default="push-t")
    ap.add_argument("--out", type=Path, default=Path("/tmp/study_pusht"))
    ap.add_argument("--size", default="small")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--device", default="cpu", help="the evaluations' Warp device (cpu, cuda, cuda:N)")
    ap.add_argument("--read", type=Path, default=None, help="print the figures of a finished study folder")
    args = ap.parse_args()

    from twinbench._runtime import quiet_warp
    from twinbench.study.evaluate import format_table

    quiet_warp()
    if args.read is not None:
        doc = json.loads((args.read / "study.json").read_text())
        total = None
    else:
        from twinbench.study.run import run_study

        t0 = time.perf_counter()
        doc = run_study(args.task, args.out, args.size, workers=args.workers, device=args.device)
        total = time.perf_counter() - t0
    print(f"task {doc['task']} size {doc['size']} cores {os.cpu_count()} device {doc.get('device', 'cpu')} "
          f"settings {doc['settings']}")
    for stage, s in doc["stage_seconds"].items():
        print(f"stage {stage} {s:.0f} s")
    for run_id, s in doc.get("evaluation_seconds", {}).items():
        print(f"evaluation {run_id} {s:.0f} s")
    if total is not None:
        print(f"total {total:.0f} s ({total / 60:.1f} min)")
    print(format_table(doc))


if __name__ == "__main__":
    main()
