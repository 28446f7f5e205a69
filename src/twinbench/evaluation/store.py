"""Results store: every evaluated episode in one SQLite file (WAL mode), safe across processes.

Each call opens its own short-lived connection, so a `ResultsStore` only holds a path: it can be
pickled into worker processes, and each `record_episode` is one committed transaction. The unique key
of an episode is (run_id, domain, policy, checkpoint, init_state, seed); recording it again replaces it.
"""

from __future__ import annotations

import json
import re
import sqlite3
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinbench.errors import InputError, StorageError, check_name, free_space

DEFAULT_DB = Path("outputs/results.sqlite")
DOMAINS = ("sim", "real", "replay")
STATUSES = ("ok", "sim_error", "policy_error")
TRUE_WORDS = ("1", "true", "yes", "success")
FALSE_WORDS = ("0", "false", "no", "failure")
INT64 = (-(2**63), 2**63 - 1)  # what an SQLite INTEGER holds
# SQLite's words for a file system that refuses a write (full, read-only, gone)
_STORAGE_WORDS = ("disk I/O error", "disk is full", "readonly database", "unable to open database file")


# ---- the one way outcomes and indices enter the store ------------------------------------------------
def parse_success(value) -> bool:
    """An episode outcome -> bool, strictly: a bool (numpy too), the integers 0 / 1 (or 0.0 / 1.0), or
    the words 1/0, true/false, yes/no, success/failure (any case). Anything else (e.g. "maybe", 2, NaN,
    None) raises InputError: `bool("false")` is True, so outcomes never go through `bool()`."""
    if isinstance(value, bool | np.bool_):
        return bool(value)
    if isinstance(value, int | np.integer | float | np.floating):
        if value == 0 or value == 1:  # NaN compares unequal to both
            return bool(value == 1)
    elif isinstance(value, str | bytes):
        text = value.decode("utf-8", "replace") if isinstance(value, bytes) else value
        word = text.strip().lower()
        if word in TRUE_WORDS:
            return True
        if word in FALSE_WORDS:
            return False
    raise InputError(f"{value!r} is not one of {', '.join(TRUE_WORDS + FALSE_WORDS)} (or a boolean): "
                     "not an outcome")


def parse_int(value, *, minimum: int | None = None, maximum: int | None = None) -> int:
    """An integer field -> int, strictly: an int (numpy too), an integral float (3.0) or a decimal string;
    never a bool, 3.7, NaN or a value outside [minimum, maximum] (and SQLite's int64). InputError."""
    if isinstance(value, bool | np.bool_):
        raise InputError(f"{value!r} is a boolean, not an integer")
    if isinstance(value, int | np.integer):
        out = int(value)
    elif isinstance(value, float | np.floating):
        if not (np.isfinite(value) and float(value).is_integer()):
            raise InputError(f"{value!r} is not an integer")
        out = int(value)
    elif isinstance(value, str):
        text = value.strip()
        if not re.fullmatch(r"[+-]?\d{1,100}", text):
            raise InputError(f"{value!r} is not an integer")
        out = int(text)
    else:
        raise InputError(f"{value!r} ({type(value).__name__}) is not an integer")
    lo = INT64[0] if minimum is None else max(minimum, INT64[0])
    hi = INT64[1] if maximum is None else min(maximum, INT64[1])
    if out < lo:
        raise InputError(f"{out} must be >= {lo}")
    if out > hi:
        raise InputError(f"{out} must be <= {hi}")
    return out


def check_run_id(run_id) -> str:
    """A run id is a name, never a path (`twinbench.errors.check_name`): it names folders under the
    output directory. InputError otherwise."""
    return check_name(run_id, "run id")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY,
    task TEXT NOT NULL,
    protocol TEXT NOT NULL,
    created REAL NOT NULL
);
CREATE TABLE IF NOT EXISTS episodes (
    run_id TEXT NOT NULL,
    task TEXT NOT NULL,
    policy TEXT NOT NULL,
    checkpoint TEXT NOT NULL,
    train_step INTEGER,
    init_state INTEGER NOT NULL,
    seed INTEGER NOT NULL,
    domain TEXT NOT NULL,
    success INTEGER NOT NULL,
    status TEXT NOT NULL,
    steps INTEGER NOT NULL,
    wall_time_s REAL NOT NULL,
    video_path TEXT,
    metrics TEXT NOT NULL,
    recorded REAL NOT NULL,
    PRIMARY KEY (run_id, domain, policy, checkpoint, init_state, seed)
);
CREATE TABLE IF NOT EXISTS run_seconds (
    run_id TEXT PRIMARY KEY,
    seconds REAL NOT NULL
);
"""

_COLUMNS = (
    "run_id", "task", "policy", "checkpoint", "train_step", "init_state", "seed", "domain",
    "success", "status", "steps", "wall_time_s", "video_path", "metrics",
)


@dataclass(frozen=True)
class EpisodeRecord:
    """One evaluated episode (sim rollout, real outcome or open-loop replay)."""

    run_id: str  # evaluation run id ("real" imports use their own run id, e.g. "real")
    task: str  # e.g. "push-t"
    policy: str  # policy name, e.g. "expert" / "act"
    checkpoint: str  # checkpoint label, "" when none (e.g. "step_20000")
    train_step: int | None  # training iteration of the checkpoint, for per-checkpoint curves
    init_state: int  # index into the task's initial-state set
    seed: int
    domain: str  # "sim" | "real" | "replay"
    success: bool
    status: str  # "ok" | "sim_error" | "policy_error"
    steps: int = 0
    wall_time_s: float = 0.0
    video_path: str | None = None
    metrics: dict = field(default_factory=dict)  # extra metrics, stored as JSON

    def __post_init__(self) -> None:
        # Strict types at the door: a string outcome like "false" must never become True, 3.7 never 3.
        object.__setattr__(self, "success", parse_success(self.success))
        ints = ("init_state", "seed", "steps") + (("train_step",) if self.train_step is not None else ())
        for name in ints:
            try:
                object.__setattr__(self, name, parse_int(getattr(self, name)))
            except InputError as err:
                raise InputError(f"EpisodeRecord.{name}: {err}") from None
        if self.domain not in DOMAINS:
            raise ValueError(f"EpisodeRecord.domain {self.domain!r} is not one of {DOMAINS}")
        if self.status not in STATUSES:
            raise ValueError(f"EpisodeRecord.status {self.status!r} is not one of {STATUSES}")
        if not isinstance(self.metrics, dict):
            raise ValueError(f"EpisodeRecord.metrics must be a dict, got {type(self.metrics).__name__}")


def _json_default(obj):
    """JSON encoder for numpy scalars/arrays (anything with .tolist()/.item())."""
    for attr in ("tolist", "item"):
        if hasattr(obj, attr):
            return getattr(obj, attr)()
    raise TypeError(f"{type(obj).__name__} is not JSON serialisable")


def _dumps(obj, what: str) -> str:
    try:
        return json.dumps(obj, sort_keys=True, default=_json_default)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{what} must be JSON-serialisable (plain values, lists, dicts): {err}") from err


def _rollback(con: sqlite3.Connection) -> None:
    """Undo the open transaction, if one is open: a signal (Ctrl-C, SIGTERM) that lands once COMMIT has
    finished leaves none, and ROLLBACK would then raise "no transaction is active" over the interrupt."""
    if con.in_transaction:
        con.execute("ROLLBACK")


class ResultsStore:
    """SQLite results store (WAL journal); one connection per call, so it is safe across processes."""

    def __init__(self, path: str | Path = DEFAULT_DB, timeout_s: float = 60.0):
        self.path = Path(path)
        self.timeout_s = float(timeout_s)
        if self.path.exists() and self.path.is_dir():
            raise InputError(f"results store path {self.path} is a directory; give a file such as "
                             f"{self.path / 'results.sqlite'}")
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
        except OSError as err:
            raise InputError(f"results store {self.path}: cannot create its folder ({err.strerror or err}); "
                             "give a --db path in a writable folder") from None
        with self._connect() as con:
            mode = con.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if mode.lower() != "wal":
                raise RuntimeError(f"{self.path}: SQLite refused WAL mode (got {mode!r}); "
                                   "put the store on a local file system")
            con.executescript(_SCHEMA)
            for table, wanted in (("runs", ("run_id", "task", "protocol", "created")),
                                  ("episodes", _COLUMNS + ("recorded",))):
                have = {r[1] for r in con.execute(f"PRAGMA table_info({table})")}
                if not set(wanted) <= have:
                    raise InputError(f"{self.path} is an SQLite file but not a twinbench results store "
                                     f"(table {table!r} lacks {sorted(set(wanted) - have)}); "
                                     "give another --db")

    def __repr__(self) -> str:
        return f"ResultsStore({str(self.path)!r})"

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        try:
            con = sqlite3.connect(self.path, timeout=self.timeout_s, isolation_level=None)
        except sqlite3.DatabaseError as err:
            raise InputError(f"cannot open results store {self.path}: {err}; give the path of a results "
                             "store (.sqlite) in a writable folder") from err
        try:
            con.execute(f"PRAGMA busy_timeout={int(self.timeout_s * 1000)}")
            yield con
        except sqlite3.DatabaseError as err:
            if "not a database" in str(err) or "malformed" in str(err):
                raise InputError(f"{self.path} is not a twinbench results store (SQLite): {err}; give "
                                 "another --db path") from err
            if isinstance(err, sqlite3.OperationalError) and any(w in str(err) for w in _STORAGE_WORDS):
                free = free_space(self.path)
                raise StorageError(f"results store {self.path}: cannot write ({err}; {free}). Free space (or "
                                   "make the folder writable) and run the same command again: episodes "
                                   "already stored are kept and a resumed run skips them") from err
            raise
        finally:
            con.close()

    def journal_mode(self) -> str:
        """The file's SQLite journal mode ("wal")."""
        with self._connect() as con:
            return con.execute("PRAGMA journal_mode").fetchone()[0]

    # ---- runs -------------------------------------------------------------------------------------
    def start_run(self, run_id: str, task: str, protocol: dict, grow: tuple[str, ...] = ()) -> list:
        """Register a run with its protocol (JSON). Idempotent: calling again with the same task and
        protocol does nothing; a different task or protocol for an existing run id raises ValueError
        (resuming must not mix protocols: use a new run id). `grow`: protocol keys that may differ when a
        run is extended by more episodes (the runner's "policies"): a stored list gains the new entries,
        another value becomes the new one; the episodes already stored keep their meaning. Returns the
        entries added to the lists. The run id must be a name (`check_run_id`)."""
        return self.start_run_with_episodes(run_id, task, protocol, [], grow=grow)

    def start_run_with_episodes(self, run_id: str, task: str, protocol: dict,
                                recs: list[EpisodeRecord], grow: tuple[str, ...] = ()) -> list:
        """`start_run` and `record_episodes(recs)` in ONE transaction: all of it is stored, or nothing
        (no empty run row is left behind when a record cannot be written)."""
        check_run_id(run_id)
        proto = _dumps(dict(protocol), "protocol")
        rows = self._episode_rows(recs)
        added: list = []
        with self._connect() as con:
            con.execute("BEGIN IMMEDIATE")
            try:
                row = con.execute("SELECT task, protocol FROM runs WHERE run_id = ?", (run_id,)).fetchone()
                if row is None:
                    con.execute("INSERT INTO runs VALUES (?, ?, ?, ?)", (run_id, task, proto, time.time()))
                elif row[0] != task or row[1] != proto:
                    old, new = json.loads(row[1]), json.loads(proto)
                    keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
                    if row[0] == task and set(keys) <= set(grow) and all(k in old and k in new for k in keys):
                        merged = dict(old)
                        for k in keys:
                            if isinstance(old[k], list) and isinstance(new[k], list):
                                gained = [v for v in new[k] if v not in old[k]]
                                added += gained
                                merged[k] = old[k] + gained
                            else:
                                merged[k] = new[k]
                        con.execute("UPDATE runs SET protocol = ? WHERE run_id = ?",
                                    (_dumps(merged, "protocol"), run_id))
                    else:
                        what = f"task {row[0]!r} != {task!r}" if row[0] != task else f"protocol keys {keys}"
                        raise InputError(f"run {run_id!r} already exists in {self.path} with a different "
                                         f"{what}; use a new run id to evaluate a different protocol")
                self._insert_episodes(con, rows)
                con.execute("COMMIT")
            except BaseException:
                _rollback(con)
                raise
        return added

    def _run_row(self, run_id: str) -> tuple[str, str]:
        """(task, protocol JSON) of a started run; KeyError when the run was never started."""
        with self._connect() as con:
            row = con.execute("SELECT task, protocol FROM runs WHERE run_id = ?", (run_id,)).fetchone()
        if row is None:
            raise KeyError(f"run {run_id!r} not found in {self.path}; known runs: {self.runs()}")
        return row

    def run_protocol(self, run_id: str) -> dict:
        """The protocol given to `start_run` (KeyError when the run was never started)."""
        return json.loads(self._run_row(run_id)[1])

    def run_task(self, run_id: str) -> str:
        """The task given to `start_run` (KeyError when the run was never started)."""
        return self._run_row(run_id)[0]

    def runs(self) -> list[str]:
        """Run ids, started ones and ones that only have episodes, sorted."""
        with self._connect() as con:
            rows = con.execute("SELECT run_id FROM runs UNION SELECT run_id FROM episodes").fetchall()
        return sorted(r[0] for r in rows)

    def add_run_seconds(self, run_id: str, seconds: float) -> None:
        """Add `seconds` of wall time spent running run `run_id`'s episodes (each evaluation or replay
        call that ran some adds its own, so a run resumed over several sessions keeps its total)."""
        with self._connect() as con:
            con.execute("INSERT INTO run_seconds VALUES (?, ?) ON CONFLICT(run_id) DO UPDATE SET "
                        "seconds = seconds + excluded.seconds", (run_id, float(seconds)))

    def run_seconds(self, run_id: str) -> float | None:
        """The wall time (s) recorded by `add_run_seconds` for run `run_id`; None where none was (a run
        stored before the store kept times, or one copied rather than run)."""
        with self._connect() as con:
            row = con.execute("SELECT seconds FROM run_seconds WHERE run_id = ?", (run_id,)).fetchone()
        return None if row is None else float(row[0])

    # ---- episodes ---------------------------------------------------------------------------------
    def record_episode(self, rec: EpisodeRecord) -> None:
        """Store one episode in its own committed transaction; the same key recorded again replaces it."""
        self.record_episodes([rec])

    def record_episodes(self, recs: list[EpisodeRecord]) -> None:
        """Store several episodes atomically (all or none), e.g. a validated CSV import."""
        rows = self._episode_rows(recs)
        with self._connect() as con:
            con.execute("BEGIN IMMEDIATE")
            try:
                self._insert_episodes(con, rows)
                con.execute("COMMIT")
            except BaseException:
                _rollback(con)
                raise

    @staticmethod
    def _episode_rows(recs: list[EpisodeRecord]) -> list[tuple]:
        """Validated SQL rows (before any transaction starts)."""
        rows = []
        for rec in recs:
            if not isinstance(rec, EpisodeRecord):
                raise TypeError(f"expected EpisodeRecord, got {type(rec).__name__}")
            rows.append((
                rec.run_id, rec.task, rec.policy, rec.checkpoint,
                None if rec.train_step is None else int(rec.train_step),
                int(rec.init_state), int(rec.seed), rec.domain, int(rec.success), rec.status,
                int(rec.steps), float(rec.wall_time_s),
                None if rec.video_path is None else str(rec.video_path),
                _dumps(rec.metrics, "EpisodeRecord.metrics"), time.time(),
            ))
        return rows

    @staticmethod
    def _insert_episodes(con: sqlite3.Connection, rows: list[tuple]) -> None:
        if rows:
            cols = ", ".join(_COLUMNS + ("recorded",))
            marks = ", ".join("?" * (len(_COLUMNS) + 1))
            con.executemany(f"INSERT OR REPLACE INTO episodes ({cols}) VALUES ({marks})", rows)

    def finished(self, run_id: str, domain: str = "sim") -> set[tuple[str, str, int, int]]:
        """{(policy, checkpoint, init_state, seed)} already recorded for this run and domain."""
        with self._connect() as con:
            rows = con.execute(
                "SELECT policy, checkpoint, init_state, seed FROM episodes WHERE run_id = ? AND domain = ?",
                (run_id, domain),
            ).fetchall()
        return {(p, c, int(i), int(s)) for p, c, i, s in rows}

    def episodes(self, run_id: str | None = None, *, domain: str | None = None,
                 task: str | None = None) -> list[EpisodeRecord]:
        """Stored episodes, filtered; ordered by run, domain, policy, checkpoint, init_state, seed."""
        where, args = [], []
        for col, val in (("run_id", run_id), ("domain", domain), ("task", task)):
            if val is not None:
                where.append(f"{col} = ?")
                args.append(val)
        sql = f"SELECT {', '.join(_COLUMNS)} FROM episodes"
        if where:
            sql += " WHERE " + " AND ".join(where)
        sql += " ORDER BY run_id, domain, policy, checkpoint, init_state, seed"
        with self._connect() as con:
            rows = con.execute(sql, args).fetchall()
        out = []
        for r in rows:
            d = dict(zip(_COLUMNS, r, strict=True))
            d["success"] = bool(d["success"])
            d["metrics"] = json.loads(d["metrics"])
            out.append(EpisodeRecord(**d))
        return out
