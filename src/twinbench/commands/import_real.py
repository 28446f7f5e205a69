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
    notes]) into the results store."""

    file: Annotated[Path, tyro.conf.Positional]
    """CSV file of real-robot outcomes."""
    db: Path = DEFAULT_DB
    """results store (SQLite)."""
    run_id: str = "real"
    """run id the real outcomes are stored under."""
    task: str = "push-t"
    """task of rows whose task column is empty or absent."""


def main(config: ImportRealConfig) -> int:
    """Bad input raises InputError: `twinbench` prints it (every bad row) and exits with code 2."""
    records = import_real_csv(config.file, ResultsStore(config.db), run_id=config.run_id, task=config.task)
    n_ok = sum(r.success for r in records)
    policies = sorted({(r.policy, r.checkpoint) for r in records})
    print(f"imported {len(records)} real episodes ({n_ok} successes) for {len(policies)} "
          f"policy/checkpoint pair(s) into {config.db} run {config.run_id!r}")
    return 0
