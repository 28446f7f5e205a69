"""Results store: every evaluated episode in one SQLite file (WAL mode), safe across processes.

Each call opens its own short-lived connection, so a `ResultsStore` only holds a path: it can be
pickled into worker processes, and each `record_episode` is one committed transaction. The unique key
of an episode is (run_id, domain, policy, checkpoint, init_state, seed); recording it again replaces it.
"""

from __future__ import annotations

import json
import sqlite3
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

DEFAULT_DB = Path("outputs/results.sqlite")
DOMAINS = ("sim", "real", "replay")
STATUSES = ("ok", "sim_error", "policy_error")

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


class ResultsStore:
    """SQLite results store (WAL journal); one connection per call, so it is safe across processes."""

    def __init__(self, path: str | Path = DEFAULT_DB, timeout_s: float = 60.0):
        self.path = Path(path)
        self.timeout_s = float(timeout_s)
        if self.path.exists() and self.path.is_dir():
            raise ValueError(f"results store path {self.path} is a directory; give a file such as "
                             f"{self.path / 'results.sqlite'}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        with self._connect() as con:
            mode = con.execute("PRAGMA journal_mode=WAL").fetchone()[0]
            if mode.lower() != "wal":
                raise RuntimeError(f"{self.path}: SQLite refused WAL mode (got {mode!r}); "
                                   "put the store on a local file system")
            con.executescript(_SCHEMA)

    def __repr__(self) -> str:
        return f"ResultsStore({str(self.path)!r})"

    @contextmanager
    def _connect(self) -> Iterator[sqlite3.Connection]:
        try:
            con = sqlite3.connect(self.path, timeout=self.timeout_s, isolation_level=None)
        except sqlite3.DatabaseError as err:
            raise ValueError(f"cannot open results store {self.path}: {err}") from err
        try:
            con.execute(f"PRAGMA busy_timeout={int(self.timeout_s * 1000)}")
            yield con
        except sqlite3.DatabaseError as err:
            if "not a database" in str(err) or "malformed" in str(err):
                raise ValueError(f"{self.path} is not a twinbench results store (SQLite): {err}") from err
            raise
        finally:
            con.close()

    def journal_mode(self) -> str:
        """The file's SQLite journal mode ("wal")."""
        with self._connect() as con:
            return con.execute("PRAGMA journal_mode").fetchone()[0]

    # ---- runs -------------------------------------------------------------------------------------
    def start_run(self, run_id: str, task: str, protocol: dict) -> None:
        """Register a run with its protocol (JSON). Idempotent: calling again with the same task and
        protocol does nothing; a different task or protocol for an existing run id raises ValueError
        (resuming must not mix protocols: use a new run id)."""
        if not run_id:
            raise ValueError("run_id must be a non-empty string")
        proto = _dumps(dict(protocol), "protocol")
        with self._connect() as con:
            con.execute("BEGIN IMMEDIATE")
            try:
                row = con.execute("SELECT task, protocol FROM runs WHERE run_id = ?", (run_id,)).fetchone()
                if row is None:
                    con.execute("INSERT INTO runs VALUES (?, ?, ?, ?)", (run_id, task, proto, time.time()))
                elif row[0] != task or row[1] != proto:
                    old, new = json.loads(row[1]), json.loads(proto)
                    keys = sorted(k for k in set(old) | set(new) if old.get(k) != new.get(k))
                    what = f"task {row[0]!r} != {task!r}" if row[0] != task else f"protocol keys {keys}"
                    raise ValueError(f"run {run_id!r} already exists in {self.path} with a different "
                                     f"{what}; use a new run id to evaluate a different protocol")
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise

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

    # ---- episodes ---------------------------------------------------------------------------------
    def record_episode(self, rec: EpisodeRecord) -> None:
        """Store one episode in its own committed transaction; the same key recorded again replaces it."""
        self.record_episodes([rec])

    def record_episodes(self, recs: list[EpisodeRecord]) -> None:
        """Store several episodes atomically (all or none), e.g. a validated CSV import."""
        rows = []
        for rec in recs:
            if not isinstance(rec, EpisodeRecord):
                raise TypeError(f"expected EpisodeRecord, got {type(rec).__name__}")
            rows.append((
                rec.run_id, rec.task, rec.policy, rec.checkpoint,
                None if rec.train_step is None else int(rec.train_step),
                int(rec.init_state), int(rec.seed), rec.domain, int(bool(rec.success)), rec.status,
                int(rec.steps), float(rec.wall_time_s),
                None if rec.video_path is None else str(rec.video_path),
                _dumps(rec.metrics, "EpisodeRecord.metrics"), time.time(),
            ))
        cols = ", ".join(_COLUMNS + ("recorded",))
        marks = ", ".join("?" * (len(_COLUMNS) + 1))
        with self._connect() as con:
            con.execute("BEGIN IMMEDIATE")
            try:
                con.executemany(f"INSERT OR REPLACE INTO episodes ({cols}) VALUES ({marks})", rows)
                con.execute("COMMIT")
            except BaseException:
                con.execute("ROLLBACK")
                raise

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
