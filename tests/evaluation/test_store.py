"""ResultsStore: round trip, WAL mode, replace-on-rerecord, finished(), concurrent writers."""

from __future__ import annotations

import multiprocessing as mp
import pickle
import sqlite3

import numpy as np
import pytest

from twinbench.evaluation.store import EpisodeRecord, ResultsStore


def _rec(**kw) -> EpisodeRecord:
    base = dict(run_id="r1", task="push-t", policy="act", checkpoint="step_100", train_step=100,
                init_state=0, seed=0, domain="sim", success=True, status="ok")
    base.update(kw)
    return EpisodeRecord(**base)


def test_round_trip_all_fields(tmp_path):
    store = ResultsStore(tmp_path / "sub" / "res.sqlite")
    rec = _rec(steps=1800, wall_time_s=12.5, video_path="/tmp/v.mp4",
               metrics={"final_dist": 0.01, "arr": np.arange(3), "n": np.int64(4)})
    none_step = _rec(checkpoint="", train_step=None, init_state=3, seed=7, success=False, status="sim_error")
    store.record_episode(rec)
    store.record_episode(none_step)
    got = store.episodes("r1")
    assert len(got) == 2
    # ordered by checkpoint: "" before "step_100"
    assert got[0] == none_step
    assert got[1].metrics == {"final_dist": 0.01, "arr": [0, 1, 2], "n": 4}
    assert got[1].steps == 1800 and got[1].wall_time_s == 12.5 and got[1].video_path == "/tmp/v.mp4"
    assert got[1].train_step == 100 and got[1].success is True
    # a new store object on the same file sees the same data
    assert ResultsStore(tmp_path / "sub" / "res.sqlite").episodes() == got


def test_wal_mode_on(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    assert store.journal_mode() == "wal"
    con = sqlite3.connect(tmp_path / "r.sqlite")
    assert con.execute("PRAGMA journal_mode").fetchone()[0] == "wal"
    con.close()


def test_rerecording_replaces(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    store.record_episode(_rec(success=False, steps=5))
    store.record_episode(_rec(success=True, steps=9))
    got = store.episodes()
    assert len(got) == 1 and got[0].success and got[0].steps == 9
    # a different domain with the same key is a different episode
    store.record_episode(_rec(domain="real", success=False))
    assert len(store.episodes()) == 2
    assert [e.success for e in store.episodes(domain="real")] == [False]


def test_finished_and_filters(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    for i in range(3):
        store.record_episode(_rec(init_state=i, seed=10 + i))
    store.record_episode(_rec(run_id="r2", init_state=5))
    store.record_episode(_rec(domain="replay", init_state=9))
    store.record_episode(_rec(task="rope", policy="expert", checkpoint="", init_state=1))
    assert store.finished("r1") == {("act", "step_100", i, 10 + i) for i in range(3)} | {
        ("expert", "", 1, 0)}
    assert store.finished("r1", domain="replay") == {("act", "step_100", 9, 0)}
    assert store.finished("nope") == set()
    assert len(store.episodes(task="rope")) == 1
    assert len(store.episodes("r1", domain="sim", task="push-t")) == 3
    assert store.runs() == ["r1", "r2"]


def test_start_run_idempotent_and_protocol(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    proto = {"task": "push-t", "init_states": [[0.0, 0.1, 45.0]], "episodes": 16, "seeds": [0, 1],
             "versions": {"twinbench": "0.1.0"}}
    store.start_run("r1", "push-t", proto)
    store.start_run("r1", "push-t", dict(proto))  # same again: no-op
    assert store.run_protocol("r1") == proto
    assert store.run_task("r1") == "push-t"
    assert store.runs() == ["r1"]
    with pytest.raises(ValueError, match="different protocol keys \\['episodes'\\]"):
        store.start_run("r1", "push-t", {**proto, "episodes": 20})
    with pytest.raises(ValueError, match="different task"):
        store.start_run("r1", "rope", proto)
    with pytest.raises(KeyError, match="not found"):
        store.run_protocol("missing")
    with pytest.raises(KeyError, match="'missing' not found"):
        store.run_task("missing")


def test_bad_input_rejected(tmp_path):
    with pytest.raises(ValueError, match="domain"):
        _rec(domain="simulation")
    with pytest.raises(ValueError, match="status"):
        _rec(status="failed")
    store = ResultsStore(tmp_path / "r.sqlite")
    with pytest.raises(ValueError, match="JSON"):
        store.record_episode(_rec(metrics={"x": object()}))
    assert store.episodes() == []
    bad = tmp_path / "notdb.sqlite"
    bad.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(ValueError, match="notdb.sqlite"):
        ResultsStore(bad)
    with pytest.raises(ValueError, match="directory"):
        ResultsStore(tmp_path)


def test_picklable(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    clone = pickle.loads(pickle.dumps(store))
    clone.record_episode(_rec())
    assert len(store.episodes()) == 1


def _writer(path: str, worker: int, n: int) -> None:
    store = ResultsStore(path)
    for i in range(n):
        store.record_episode(_rec(policy=f"p{worker}", init_state=i, seed=worker, success=bool(i % 2)))


def test_concurrent_processes_lose_nothing(tmp_path):
    path = str(tmp_path / "r.sqlite")
    ResultsStore(path)
    n_workers, n = 4, 40
    ctx = mp.get_context("spawn")
    procs = [ctx.Process(target=_writer, args=(path, w, n)) for w in range(n_workers)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
        assert p.exitcode == 0
    store = ResultsStore(path)
    assert store.finished("r1") == {(f"p{w}", "step_100", i, w) for w in range(n_workers) for i in range(n)}
    assert sum(e.success for e in store.episodes()) == n_workers * n // 2


class _FullDisk:
    """A connection whose writes fail as SQLite's do on a full disk (reads pass through)."""

    def __init__(self, con: sqlite3.Connection) -> None:
        self._con = con

    def execute(self, sql: str, *args):
        if sql.startswith("BEGIN"):
            raise sqlite3.OperationalError("database or disk is full")
        return self._con.execute(sql, *args)

    def close(self) -> None:
        self._con.close()


def test_a_refused_write_is_a_storage_error_naming_the_file_and_the_fix(tmp_path, monkeypatch):
    from twinbench.errors import StorageError

    store = ResultsStore(tmp_path / "r.sqlite")
    store.record_episode(_rec(seed=0))
    real_connect = sqlite3.connect
    monkeypatch.setattr(sqlite3, "connect", lambda *a, **k: _FullDisk(real_connect(*a, **k)))
    with pytest.raises(StorageError, match=r"r\.sqlite: cannot write \(database or disk is full; .* free on "
                                           r".*\)\. Free space .* episodes already stored are kept"):
        store.record_episode(_rec(seed=1))
    monkeypatch.undo()
    store.record_episode(_rec(seed=1))
    assert [e.seed for e in store.episodes()] == [0, 1]


def test_a_full_file_system_keeps_what_was_stored(tmp_path):
    """On a real tmpfs filled to the last byte (needs root and mount; skipped elsewhere)."""
    import os
    import subprocess

    from twinbench.errors import StorageError

    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=512k", "tmpfs", str(disk)],
                                           capture_output=True).returncode != 0:
        pytest.skip("mounting a small tmpfs needs root and mount(8)")
    try:
        store = ResultsStore(disk / "results.sqlite")
        store.record_episode(_rec(seed=0))
        filler = disk / "filler"
        with pytest.raises(OSError), filler.open("wb") as fh:
            while True:
                fh.write(b"\0" * 4096)
                fh.flush()
        with pytest.raises(StorageError, match="results.sqlite: cannot write"):
            for seed in range(1, 200):  # the WAL's free pages may take a few episodes before it grows
                store.record_episode(_rec(seed=seed, metrics={"pad": "x" * 2000}))
        filler.unlink()
        stored = store.episodes()
        assert stored[0].seed == 0 and [e.seed for e in stored] == list(range(len(stored)))
        store.record_episode(_rec(seed=500))
        assert store.episodes()[-1].seed == 500
    finally:
        subprocess.run(["umount", str(disk)], capture_output=True)


def test_run_seconds_add_up_and_a_store_from_before_them_gains_the_table(tmp_path):
    """Each session's time on a run adds to its total (a study resumed over days reports all of it); a
    results file written before the store kept times (no run_seconds table) opens and gains it."""
    path = tmp_path / "old.sqlite"
    con = sqlite3.connect(path)
    con.executescript("CREATE TABLE runs (run_id TEXT PRIMARY KEY, task TEXT NOT NULL, protocol TEXT NOT "
                      "NULL, created REAL NOT NULL);")
    con.close()
    store = ResultsStore(path)
    store.record_episode(_rec())  # the episodes table was created too
    assert store.run_seconds("r1") is None
    store.add_run_seconds("r1", 12.5)
    store.add_run_seconds("r1", 7.25)
    store.add_run_seconds("r2", 1.0)
    assert store.run_seconds("r1") == 19.75 and ResultsStore(path).run_seconds("r2") == 1.0


def test_an_interrupt_right_after_commit_propagates_as_itself(tmp_path, monkeypatch):
    """SIGTERM / Ctrl-C landing once COMMIT has finished: the interrupt propagates (it was hidden by
    sqlite's "cannot rollback - no transaction is active", an internal error in `twinbench eval`), and the
    committed episode is kept."""
    from contextlib import contextmanager

    store = ResultsStore(tmp_path / "r.sqlite")
    store.start_run("r1", "push-t", {"task": "push-t"})
    connect = ResultsStore._connect

    class InterruptAfterCommit:
        def __init__(self, con):
            self._con = con

        def __getattr__(self, name):
            return getattr(self._con, name)

        def execute(self, sql, *args):
            out = self._con.execute(sql, *args)
            if sql == "COMMIT":
                raise KeyboardInterrupt
            return out

    @contextmanager
    def interrupted(self):
        with connect(self) as con:
            yield InterruptAfterCommit(con)

    monkeypatch.setattr(ResultsStore, "_connect", interrupted)
    with pytest.raises(KeyboardInterrupt):
        store.record_episode(_rec())
    with pytest.raises(KeyboardInterrupt):
        store.start_run("r2", "push-t", {"task": "push-t"})
    monkeypatch.undo()
    assert [r.run_id for r in store.episodes("r1")] == ["r1"]
    assert store.run_protocol("r2") == {"task": "push-t"}
