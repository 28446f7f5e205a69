"""Import real-robot episode outcomes from a CSV file into the results store (domain "real").

Columns: policy, checkpoint, init_state, success (required); train_step, seed, task, notes and any
final task metric named `final_<metric>` (e.g. `final_msd`, a number; optional). Row numbers in error
messages count the header as row 1, as a spreadsheet shows them. The whole file is validated first;
nothing is imported when any row is bad.

One import is one task: `task` (`import-real --task`) or, when it is not given, the CSV's task column,
which must then name one task on every row; never a default. `init_state` is an index into the task's
grid (the built-in grids are the reference study's, in its order); rows indexed in another order come in
through an index map (`evaluation.grids.read_index_map`), and keep their own index as
`metrics["study_index"]`. The run's protocol records the task, its grid (`grids.grid_info`) and the map.
"""

from __future__ import annotations

import csv
from pathlib import Path

from twinbench.errors import InputError
from twinbench.evaluation.grids import grid_info, map_index, read_index_map
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
FINAL_PREFIX = "final_"  # columns final_<metric>: the task's metrics at the episode's last frame
_MAX_REPORTED = 20


def _parse_int(text: str, *, minimum: int | None = None) -> int:
    return parse_int(text, minimum=minimum)


def _final_value(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise InputError(f"{text!r} is not a number") from None
    if value != value or value in (float("inf"), float("-inf")):
        raise InputError(f"{text!r} is not a finite number")
    return value


def read_real_csv(path: str | Path, run_id: str = "real", task: str | None = None,
                  index_map: dict[int, int] | None = None) -> list[EpisodeRecord]:
    """Validate a real-outcome CSV and return its episodes (domain "real", status "ok"), all of one task:
    `task`, else the one task the CSV's task column names. `index_map` maps the CSV's init_state values
    (another study's indices) to ours.

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
    unknown = [h for h in header if h not in REQUIRED + OPTIONAL and not h.startswith(FINAL_PREFIX)]
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
                         f"{', '.join(REQUIRED)} and optionally {', '.join(OPTIONAL)}, "
                         f"{FINAL_PREFIX}<metric>")

    if task is None and "task" not in header:
        from twinbench.tasks import task_names

        raise InputError(f"{path}: no task column and no --task: give --task TASK (one of "
                         f"{', '.join(task_names())}) or a task column; outcomes are never assumed to be "
                         "of some default task")
    errors: list[str] = []
    records: list[EpisodeRecord] = []
    given_task = task
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
        init_state = check("init_state", lambda t: map_index(index_map, _parse_int(t, minimum=0),
                                                             "the index map"))
        success = check("success", parse_success)
        train_step = None
        if cells.get("train_step", "").strip():
            train_step = check("train_step", lambda t: _parse_int(t, minimum=0))
        seed = check("seed", _parse_int) if cells.get("seed", "").strip() else 0
        row_task = cells.get("task", "").strip() or given_task
        if row_task is None:
            errors.append(f"{path} row {line}, column task: empty, and no --task given (give --task TASK "
                          "or fill the task column)")
        elif task is not None and row_task != task:
            errors.append(f"{path} row {line}, column task: {row_task!r}, but this import is of task "
                          f"{task!r}; import each task's rows under its own --run-id")
        else:
            task = row_task  # the first row's task: every later row must name it too
        notes = cells.get("notes", "").strip()
        final = {h[len(FINAL_PREFIX):]: check(h, _final_value) for h in header
                 if h.startswith(FINAL_PREFIX) and cells[h].strip()}
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
        extra = {"notes": notes} if notes else {}
        if index_map is not None:
            extra["study_index"] = _parse_int(cells["init_state"])
        if final:
            extra["final"] = final
        records.append(EpisodeRecord(
            run_id=run_id, task=row_task, policy=policy, checkpoint=checkpoint, train_step=train_step,
            init_state=init_state, seed=seed, domain="real", success=success, status="ok", metrics=extra,
        ))
    if errors:
        more = f"\n... and {len(errors) - _MAX_REPORTED} more" if len(errors) > _MAX_REPORTED else ""
        raise InputError(f"{len(errors)} problem(s) in {path}; nothing was imported:\n"
                         + "\n".join(errors[:_MAX_REPORTED]) + more)
    if not records:
        raise InputError(f"{path} has a header but no data rows")
    return records


def import_real_csv(path: str | Path, store: ResultsStore, run_id: str = "real", task: str | None = None,
                    index_map: str | Path | None = None) -> list[EpisodeRecord]:
    """Validate the CSV, then record all of its episodes in one transaction (all or nothing). `task`:
    the task of every row (None: the one task of the CSV's task column); `index_map`: a CSV/JSON map from
    the CSV's init_state values to ours (`grids.read_index_map`).

    Importing the same trials again replaces them (same run id, policy, checkpoint, init_state, seed)."""
    from twinbench.tasks import get_task

    if task is not None:
        get_task(task)  # an unknown --task is refused before the file is read
    mapping = None
    if index_map is not None:
        if task is None:
            raise InputError("--index-map needs --task (the map's init_state values index that task's grid)")
        mapping = read_index_map(index_map, get_task(task).n_grid_states)
    records = read_real_csv(path, run_id=run_id, task=task, index_map=mapping)
    task = records[0].task
    try:
        grid = grid_info(task)
    except ValueError as err:
        raise InputError(f"{path}: column task: {err}") from None
    protocol = {"kind": "real-robot outcomes", "task": task, "grid": grid,
                "index_map": None if mapping is None else {str(k): v for k, v in sorted(mapping.items())}}
    store.start_run_with_episodes(run_id, task, protocol, records)
    return records
