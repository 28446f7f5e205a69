"""Outcomes and run ids (issue 14): one strict parser everywhere outcomes enter, no silent 3.7 -> 3,
out-of-grid replay states refused, run ids are names, import-real all-or-nothing."""

from __future__ import annotations

import json

import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from test_replay import write_lerobot_v3

from twinbench.cli import main as cli_main
from twinbench.errors import InputError
from twinbench.evaluation import real as real_module
from twinbench.evaluation.real import import_real_csv
from twinbench.evaluation.replay import load_recorded, replay_episodes
from twinbench.evaluation.store import EpisodeRecord, ResultsStore, parse_int, parse_success

ACTS = np.zeros((3, 2)).tolist()


@pytest.mark.parametrize("value, expected", [
    (True, True), (False, False), (np.bool_(False), False), (1, True), (0, False), (np.int64(0), False),
    (1.0, True), (0.0, False), ("false", False), ("No", False), (" failure ", False), ("0", False),
    ("TRUE", True), ("yes", True), ("success", True), (b"false", False), (np.str_("no"), False),
])
def test_parse_success_accepts_only_clear_outcomes(value, expected):
    assert parse_success(value) is expected


@pytest.mark.parametrize("value", ["maybe", "", "2", 2, -1, 0.5, float("nan"), None, [], "truee"])
def test_parse_success_refuses_everything_else(value):
    with pytest.raises(InputError, match="is not one of"):
        parse_success(value)


def test_parse_int_is_strict():
    assert parse_int("12") == 12 and parse_int(3.0) == 3 and parse_int(np.int32(-4)) == -4
    for bad in (3.7, "3.7", True, np.nan, float("inf"), "1e3", None, "12abc"):
        with pytest.raises(InputError):
            parse_int(bad)
    with pytest.raises(InputError, match="must be <= 9223372036854775807"):
        parse_int("99999999999999999999")
    with pytest.raises(InputError, match="must be >= 0"):
        parse_int(-1, minimum=0)


def test_the_record_itself_never_coerces_a_string_outcome():
    rec = EpisodeRecord("r", "t", "p", "", None, 0, 0, "real", "false", "ok")
    assert rec.success is False
    with pytest.raises(InputError, match="init_state"):
        EpisodeRecord("r", "t", "p", "", None, 3.7, 0, "real", True, "ok")


def _json_log(tmp_path, **fields):
    ep = {"init_state": 1, "actions": ACTS, "success": True, "policy": "p", "checkpoint": "c", **fields}
    path = tmp_path / "log.json"
    path.write_text(json.dumps({"episodes": [ep]}))
    return path


@pytest.mark.parametrize("word", ["false", "no", "False", "0", "failure"])
def test_json_npz_and_parquet_false_words_are_failures(tmp_path, word):
    assert load_recorded(_json_log(tmp_path, success=word))[0].success is False
    npz = tmp_path / "log.npz"
    np.savez(npz, init_state=np.array([1]), success=np.array([word]), policy=np.array(["p"]),
             checkpoint=np.array(["c"]), lengths=np.array([3]), actions=np.zeros((3, 2)))
    assert load_recorded(npz)[0].success is False
    ds = tmp_path / "ds"
    write_lerobot_v3(ds)
    meta = ds / "meta" / "episodes" / "chunk-000" / "file-000.parquet"
    table = pq.read_table(meta).to_pydict()
    table["success"] = [word] * len(table["success"])
    pq.write_table(pa.table(table), meta)
    assert [e.success for e in load_recorded(ds)] == [False] * len(table["success"])


def test_lerobot_outcomes_file_false_words(tmp_path):
    ds = tmp_path / "ds"
    write_lerobot_v3(ds, with_outcomes=False)
    outcomes = tmp_path / "out.json"
    outcomes.write_text(json.dumps([{"episode_index": i, "init_state": i, "success": "no", "policy": "p",
                                     "checkpoint": ""} for i in range(5)]))
    assert [e.success for e in load_recorded(ds, outcomes)] == [False] * 5


@pytest.mark.parametrize("fields, needle", [
    ({"success": "maybe"}, "field 'success'"),
    ({"init_state": 3.7}, "field 'init_state': 3.7 is not an integer"),
    ({"init_state": True}, "field 'init_state'"),
    ({"init_state": "1"}, None),  # a decimal string is fine
    ({"seed": 1e30}, "field 'seed'"),
    ({"policy": 5}, "field 'policy'"),
])
def test_json_log_fields_are_strict(tmp_path, fields, needle):
    path = _json_log(tmp_path, **fields)
    if needle is None:
        assert load_recorded(path)[0].init_state == 1
        return
    with pytest.raises(InputError, match=needle) as err:
        load_recorded(path)
    assert str(path) in str(err.value) and "episode 0" in str(err.value)


def test_replay_refuses_init_states_outside_the_grid(tmp_path):
    eps = load_recorded(_json_log(tmp_path, init_state=99999))
    store = ResultsStore(tmp_path / "r.sqlite")
    with pytest.raises(InputError, match=r"init_state 99999 is not a grid state of task 'point-reach' "
                                         r"\(0..7\)"):
        replay_episodes("point-reach", eps, store, "rp")
    assert store.runs() == []  # refused before anything was written
    ok = replay_episodes("point-reach", load_recorded(_json_log(tmp_path, init_state=7)), store, "rp")
    assert ok[0][1].init_state == 7


def test_bad_json_and_info_files_name_the_file(tmp_path):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    with pytest.raises(InputError, match="bad.json: not valid JSON"):
        load_recorded(bad)
    deep = tmp_path / "deep.json"
    deep.write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(InputError, match="deep.json"):
        load_recorded(deep)
    ds = tmp_path / "ds"
    write_lerobot_v3(ds)
    (ds / "meta" / "info.json").write_text("[1, 2]")
    with pytest.raises(InputError, match="info.json: expected a JSON object"):
        load_recorded(ds)
    (ds / "meta" / "info.json").write_text("\x00garbage")
    with pytest.raises(InputError, match="info.json: not valid JSON"):
        load_recorded(ds)


def test_import_real_out_of_range_integer_leaves_nothing_behind(tmp_path):
    csv = tmp_path / "r.csv"
    csv.write_text("policy,checkpoint,init_state,success,seed\na,,0,yes,99999999999999999999999\n")
    store = ResultsStore(tmp_path / "r.sqlite")
    with pytest.raises(InputError, match="column seed: 99999999999999999999999 must be <="):
        import_real_csv(csv, store, run_id="lab", task="push-t")
    assert store.runs() == [] and store.episodes() == []


def test_import_real_is_one_transaction(tmp_path, monkeypatch):
    csv = tmp_path / "r.csv"
    csv.write_text("policy,checkpoint,init_state,success\na,,0,yes\na,,1,no\n")
    store = ResultsStore(tmp_path / "r.sqlite")

    original = ResultsStore._episode_rows

    def broken(recs):  # a row that passes validation but fails inside the transaction
        rows = original(recs)
        rows[1] = rows[1][:5] + (2**70,) + rows[1][6:]
        return rows

    monkeypatch.setattr(ResultsStore, "_episode_rows", staticmethod(broken))
    with pytest.raises(OverflowError):
        import_real_csv(csv, store, run_id="lab", task="push-t")
    monkeypatch.undo()
    assert store.runs() == [] and store.episodes() == []  # no empty run row, no half import
    assert len(import_real_csv(csv, store, run_id="lab", task="push-t")) == 2 and store.runs() == ["lab"]
    assert real_module.parse_success is parse_success  # one parser, shared


@pytest.mark.parametrize("run_id", ["../../x", "/abs/path", "a/b", ".."])
def test_run_ids_are_names_for_import_real_and_replay(tmp_path, run_id):
    csv = tmp_path / "r.csv"
    csv.write_text("policy,checkpoint,init_state,success\na,,0,yes\n")
    store = ResultsStore(tmp_path / "r.sqlite")
    with pytest.raises(InputError, match="run id"):
        import_real_csv(csv, store, run_id=run_id, task="push-t")
    with pytest.raises(InputError, match="run id"):
        replay_episodes("point-reach", load_recorded(_json_log(tmp_path)), store, run_id)
    with pytest.raises(InputError, match="run id"):
        store.start_run(run_id, "t", {})
    assert store.runs() == []


def test_store_of_another_schema_is_one_line(tmp_path, capsys):
    import sqlite3

    other = tmp_path / "other.sqlite"
    con = sqlite3.connect(other)
    con.execute("CREATE TABLE episodes (id INTEGER, name TEXT)")
    con.commit()
    con.close()
    with pytest.raises(InputError, match="not a twinbench results store"):
        ResultsStore(other)
    assert cli_main(["report", "--run-id", "x", "--db", str(other), "--out", str(tmp_path / "r.html")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "other.sqlite" in err[0]
