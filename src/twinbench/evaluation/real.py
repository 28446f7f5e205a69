"""Import real-robot episode outcomes from a CSV file into the results store (domain "real").

Columns: policy, checkpoint, init_state, success (required); train_step, seed, task, notes (optional).
Row numbers in error messages count the header as row 1, as a spreadsheet shows them. The whole file is
validated first; nothing is imported when any row is bad.
"""

from __future__ import annotations

import csv
from pathlib import Path

from twinbench.errors import InputError
from twinbench.evaluation.store import (  # noqa: F401 - parse_success/TRUE_WORDS/FALSE_WORDS re-exported
    FALSE_WORDS,
    TRUE_WORDS,
    EpisodeRecord,
    ResultsStore,
    check_run_id,
    parse_int,
    parse_success,
)

REQUIRED = ("policy", "checkpoint", "init_state", "success")
OPTIONAL = ("train_step", "seed", "task", "notes")
_MAX_REPORTED = 20


def _parse_int(text: str, *, minimum: int | None = None) -> int:
    return parse_int(text, minimum=minimum)


def read_real_csv(path: str | Path, run_id: str = "real", task: str = "push-t") -> list[EpisodeRecord]:
    """Validate a real-outcome CSV and return its episodes (domain "real", status "ok").

    Raises InputError (a ValueError) listing every bad row as "FILE row N, column C: problem"."""
    check_run_id(run_id)
    path = Path(path)
    if not path.is_file():
        raise InputError(f"real-outcome CSV {path} does not exist (give the path of a .csv file)")
    try:
        with path.open(newline="", encoding="utf-8-sig") as fh:
            rows = list(csv.reader(fh))
    except UnicodeDecodeError as err:
        raise InputError(f"{path} is not UTF-8 text: {err}; save it as UTF-8 CSV") from err
    except csv.Error as err:
        raise InputError(f"{path} is not a valid CSV file: {err}") from err
    if not rows or not any(cell.strip() for cell in rows[0]):
        raise InputError(f"{path} is empty: expected a header row with columns {', '.join(REQUIRED)}")
    header = [h.strip().lower() for h in rows[0]]
    missing = [c for c in REQUIRED if c not in header]
    unknown = [h for h in header if h not in REQUIRED + OPTIONAL]
    dupes = sorted({h for h in header if header.count(h) > 1})
    if missing or unknown or dupes:
        parts = []
        if missing:
            parts.append(f"missing column(s) {', '.join(missing)}")
        if unknown:
            parts.append(f"unknown column(s) {', '.join(repr(u) for u in unknown)}")
        if dupes:
            parts.append(f"repeated column(s) {', '.join(dupes)}")
        raise InputError(f"{path} row 1 (header): {'; '.join(parts)}. Expected columns "
                         f"{', '.join(REQUIRED)} and optionally {', '.join(OPTIONAL)}")

    errors: list[str] = []
    records: list[EpisodeRecord] = []
    seen: dict[tuple, int] = {}
    steps: dict[tuple[str, str], tuple[int | None, int]] = {}
    for line, row in enumerate(rows[1:], start=2):
        if not any(cell.strip() for cell in row):
            continue  # blank line
        if len(row) != len(header):
            errors.append(f"{path} row {line}: {len(row)} fields, the header has {len(header)}")
            continue
        cells = dict(zip(header, row, strict=True))
        bad = len(errors)

        def check(column, parse, cells=cells, line=line):
            try:
                return parse(cells[column])
            except ValueError as err:
                errors.append(f"{path} row {line}, column {column}: {err}")
                return None

        policy = cells["policy"].strip()
        if not policy:
            errors.append(f"{path} row {line}, column policy: empty (give the policy name)")
        checkpoint = cells["checkpoint"].strip()
        init_state = check("init_state", lambda t: _parse_int(t, minimum=0))
        success = check("success", parse_success)
        train_step = None
        if cells.get("train_step", "").strip():
            train_step = check("train_step", lambda t: _parse_int(t, minimum=0))
        seed = check("seed", _parse_int) if cells.get("seed", "").strip() else 0
        row_task = cells.get("task", "").strip() or task
        notes = cells.get("notes", "").strip()
        if len(errors) > bad:
            continue
        key = (policy, checkpoint, init_state, seed)
        if key in seen:
            errors.append(f"{path} row {line}: repeats row {seen[key]}'s (policy, checkpoint, init_state, "
                          f"seed) = {key}; give repeated trials distinct seeds")
            continue
        seen[key] = line
        prev = steps.setdefault((policy, checkpoint), (train_step, line))
        if prev[0] != train_step:
            errors.append(f"{path} row {line}, column train_step: {train_step} differs from {prev[0]} on row "
                          f"{prev[1]} for the same policy {policy!r} and checkpoint {checkpoint!r}")
            continue
        records.append(EpisodeRecord(
            run_id=run_id, task=row_task, policy=policy, checkpoint=checkpoint, train_step=train_step,
            init_state=init_state, seed=seed, domain="real", success=success, status="ok",
            metrics={"notes": notes} if notes else {},
        ))
    if errors:
        more = f"\n... and {len(errors) - _MAX_REPORTED} more" if len(errors) > _MAX_REPORTED else ""
        raise InputError(f"{len(errors)} problem(s) in {path}; nothing was imported:\n"
                         + "\n".join(errors[:_MAX_REPORTED]) + more)
    if not records:
        raise InputError(f"{path} has a header but no data rows")
    return records


def import_real_csv(path: str | Path, store: ResultsStore, run_id: str = "real",
                    task: str = "push-t") -> list[EpisodeRecord]:
    """Validate the CSV, then record all of its episodes in one transaction (all or nothing).

    Importing the same trials again replaces them (same run id, policy, checkpoint, init_state, seed)."""
    records = read_real_csv(path, run_id=run_id, task=task)
    store.start_run_with_episodes(run_id, task, {"kind": "real-robot outcomes", "task": task}, records)
    return records
