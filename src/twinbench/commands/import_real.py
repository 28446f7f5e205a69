"""`twinbench import-real`: import real-robot episode outcomes from a CSV into the results store."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro

from twinbench.evaluation.real import import_real_csv
from twinbench.evaluation.store import DEFAULT_DB, ResultsStore


@dataclass(frozen=True)
class ImportRealConfig:
    """Import real-robot outcomes (CSV: policy, checkpoint, init_state, success[, train_step, seed, task,
    notes, final_<metric>]) into the results store."""

    file: Annotated[Path, tyro.conf.Positional]
    """CSV file of real-robot outcomes."""
    db: Path = DEFAULT_DB
    """results store (SQLite)."""
    run_id: str = "real"
    """run id the real outcomes are stored under."""
    task: str | None = None
    """task of the outcomes (push-t, rope-routing, toy-packing, ...); when omitted, the CSV's task column,
    which must name one task on every row (there is no default task)."""
    index_map: Path | None = None
    """CSV (study_index,init_state) or JSON map from the CSV's init_state values to the task's grid
    indices; not needed for the reference study's indices (the built-in grids are in its order)."""


def main(config: ImportRealConfig) -> int:
    """Bad input raises InputError: `twinbench` prints it (every bad row) and exits with code 2."""
    records = import_real_csv(config.file, ResultsStore(config.db), run_id=config.run_id, task=config.task,
                              index_map=config.index_map)
    n_ok = sum(r.success for r in records)
    policies = sorted({(r.policy, r.checkpoint) for r in records})
    source = "--task" if config.task else "the CSV's task column"
    mapped = f", init_state through {config.index_map}" if config.index_map else ""
    print(f"imported {len(records)} real episodes ({n_ok} successes) of task {records[0].task!r} (from "
          f"{source}{mapped}) for {len(policies)} policy/checkpoint pair(s) into {config.db} run "
          f"{config.run_id!r}")
    return 0
