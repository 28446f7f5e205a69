"""Which initial-state grid a run's `init_state` indices refer to, and index maps from another study's
grid order to ours.

`grid_info(task, env_kwargs)` identifies a task's grid (its size and a hash of its offsets); evaluation,
`import-real` and `replay` record it in their run's protocol, so the report can tell when real and sim
episodes index different grids. The built-in tasks' grids are the reference study's, in its index order
(its state i is our init_state i); episodes indexed in another order come in through an index map
(`read_index_map`): a CSV with columns `study_index,init_state`, or JSON, either `{"STUDY_INDEX":
INIT_STATE, ...}` or a list whose position k holds the init_state of study index k.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import json
from pathlib import Path

import numpy as np

from twinbench.errors import InputError
from twinbench.evaluation.store import parse_int


def grid_info(task: str, env_kwargs: dict | None = None) -> dict:
    """{"task", "n_states", "id"} of `task`'s initial-state grid with the task settings in `env_kwargs`;
    `id` hashes the grid's offsets (rounded to 1e-6), so two runs with equal ids index the same states."""
    from twinbench.tasks import get_task

    spec = get_task(task)
    if spec.task_cls is None:  # a task with its own env: its grid is its code's
        return {"task": task, "n_states": spec.n_grid_states, "id": f"{task}-{spec.n_grid_states}"}
    names = {f.name for f in dataclasses.fields(spec.task_cls.settings_cls)}
    settings = {k: v for k, v in (env_kwargs or {}).items() if k in names}
    grid = spec.task_cls(**settings).initial_states.grid
    text = json.dumps({role: np.round(np.asarray(g, float), 6).tolist() for role, g in sorted(grid.items())})
    return {"task": task, "n_states": len(next(iter(grid.values()))),
            "id": hashlib.sha256(text.encode()).hexdigest()[:16]}


def read_index_map(path: str | Path, n_states: int) -> dict[int, int]:
    """{study index: our init_state} from a CSV or JSON index map (see the module docstring); every
    init_state in [0, n_states), each at most once. InputError naming the file and entry otherwise."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"index map {path} does not exist (a .csv with columns study_index,init_state or "
                         "a .json {\"STUDY_INDEX\": INIT_STATE})")
    try:
        if path.suffix.lower() == ".json":
            data = json.loads(path.read_text(encoding="utf-8"))
            if isinstance(data, list):
                pairs = list(enumerate(data))
            elif isinstance(data, dict):
                pairs = list(data.items())
            else:
                raise InputError(f"index map {path}: expected a JSON object or list, got "
                                 f"{type(data).__name__}")
            where = [f"{path} entry {k!r}" for k, _ in pairs]
        else:
            with path.open(newline="", encoding="utf-8-sig") as fh:
                rows = list(csv.DictReader(fh))
            if not rows or not {"study_index", "init_state"} <= {(h or "").strip() for h in rows[0]}:
                raise InputError(f"index map {path}: expected a header row with columns "
                                 "study_index,init_state")
            rows = [{(k or "").strip(): v for k, v in r.items()} for r in rows]
            pairs = [(r["study_index"], r["init_state"]) for r in rows]
            where = [f"{path} row {i}" for i in range(2, len(rows) + 2)]
    except (UnicodeDecodeError, json.JSONDecodeError, csv.Error) as err:
        raise InputError(f"index map {path}: cannot read it ({err})") from None
    out: dict[int, int] = {}
    for (study, ours), at in zip(pairs, where, strict=True):
        try:
            k, v = parse_int(study, minimum=0), parse_int(ours, minimum=0, maximum=n_states - 1)
        except InputError as err:
            raise InputError(f"{at}: {err} (study_index >= 0; init_state a grid index in "
                             f"[0, {n_states}))") from None
        if k in out:
            raise InputError(f"{at}: study index {k} is mapped twice")
        out[k] = v
    if not out:
        raise InputError(f"index map {path} is empty")
    dup = sorted({v for v in out.values() if list(out.values()).count(v) > 1})
    if dup:
        raise InputError(f"index map {path}: init_state(s) {dup} are the image of several study indices")
    return out


def map_index(index_map: dict[int, int] | None, index: int, where: str) -> int:
    """`index` through `index_map` (None: unchanged); InputError naming `where` when it is not mapped."""
    if index_map is None:
        return index
    if index not in index_map:
        raise InputError(f"{where}: index {index} is not in the index map (it maps {sorted(index_map)})")
    return index_map[index]
