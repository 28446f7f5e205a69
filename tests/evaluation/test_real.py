"""Real-outcome CSV import: accepted spellings, row/column-named errors, all-or-nothing, CLI."""

from __future__ import annotations

import json

import pytest

from twinbench.cli import main as cli_main
from twinbench.evaluation.real import import_real_csv, parse_success, read_real_csv
from twinbench.evaluation.store import ResultsStore


def _write(tmp_path, text, name="real.csv"):
    p = tmp_path / name
    p.write_text(text)
    return p


GOOD = """policy,checkpoint,init_state,success,train_step,seed,notes
act,step_1000,0,1,1000,,
act,step_1000,1,no,1000,,gripper slipped
act, step_1000 ,2,Success,1000,3,
expert,,0,TRUE,,,
expert,,1,failure,,,
"""


def test_parse_success_spellings():
    for word in ("1", "true", "True", "YES", "success", " yes "):
        assert parse_success(word) is True
    for word in ("0", "false", "No", "FAILURE"):
        assert parse_success(word) is False
    with pytest.raises(ValueError, match="'maybe' is not one of 1, true, yes, success, 0"):
        parse_success("maybe")


def test_read_good_csv(tmp_path):
    recs = read_real_csv(_write(tmp_path, GOOD), run_id="real", task="push-t")
    assert [(r.policy, r.checkpoint, r.init_state, r.seed, r.success) for r in recs] == [
        ("act", "step_1000", 0, 0, True), ("act", "step_1000", 1, 0, False),
        ("act", "step_1000", 2, 3, True), ("expert", "", 0, 0, True), ("expert", "", 1, 0, False)]
    assert [r.train_step for r in recs] == [1000, 1000, 1000, None, None]
    assert all(r.domain == "real" and r.status == "ok" and r.task == "push-t" for r in recs)
    assert recs[1].metrics == {"notes": "gripper slipped"} and recs[0].metrics == {}


def test_import_into_store_and_reimport_replaces(tmp_path):
    store = ResultsStore(tmp_path / "r.sqlite")
    path = _write(tmp_path, GOOD)
    import_real_csv(path, store, run_id="real", task="push-t")
    import_real_csv(path, store, run_id="real", task="push-t")
    eps = store.episodes("real", domain="real")
    assert len(eps) == 5 and sum(e.success for e in eps) == 3
    assert store.run_protocol("real")["task"] == "push-t"


def test_bad_value_names_row_and_column_and_imports_nothing(tmp_path):
    text = GOOD + "act,step_1000,3,maybe,1000,,\n"  # header is row 1, so this is row 7
    path = _write(tmp_path, text, "FILE.csv")
    store = ResultsStore(tmp_path / "r.sqlite")
    with pytest.raises(ValueError) as info:
        import_real_csv(path, store, task="push-t")
    assert f"{path} row 7, column success: 'maybe' is not one of" in str(info.value)
    assert "nothing was imported" in str(info.value)
    assert store.episodes() == []


def test_every_bad_row_is_reported(tmp_path):
    text = ("policy,checkpoint,init_state,success,train_step,seed\n"
            ",c,0,1,,\n"          # row 2: empty policy
            "a,c,-1,1,,\n"        # row 3: negative init_state
            "a,c,x,1,,\n"         # row 4: not an integer
            "a,c,1,1,ten,\n"      # row 5: bad train_step
            "a,c,2,1,,s\n"        # row 6: bad seed
            "a,c,3,1\n"           # row 7: short row
            "a,c,4,1,,\n"
            "a,c,4,0,,\n"         # row 9: duplicate of row 8
            "a,d,5,1,10,\n"
            "a,d,6,1,20,\n")      # row 11: train_step differs for checkpoint d
    with pytest.raises(ValueError) as info:
        read_real_csv(_write(tmp_path, text), task="push-t")
    msg = str(info.value)
    for needle in ("row 2, column policy: empty", "row 3, column init_state: -1 must be >= 0",
                   "row 4, column init_state: 'x' is not an integer", "row 5, column train_step",
                   "row 6, column seed", "row 7: 4 fields, the header has 6", "row 9: repeats row 8",
                   "row 11, column train_step: 20 differs from 10 on row 10"):
        assert needle in msg
    assert msg.startswith("8 problem(s)")


def test_header_problems(tmp_path):
    with pytest.raises(ValueError, match="row 1 \\(header\\): missing column\\(s\\) success"):
        read_real_csv(_write(tmp_path, "policy,checkpoint,init_state\na,b,0\n"))
    with pytest.raises(ValueError, match="unknown column\\(s\\) 'outcome'"):
        read_real_csv(_write(tmp_path, "policy,checkpoint,init_state,success,outcome\na,b,0,1,x\n"))
    with pytest.raises(ValueError, match="empty"):
        read_real_csv(_write(tmp_path, ""))
    with pytest.raises(ValueError, match="no data rows"):
        read_real_csv(_write(tmp_path, "policy,checkpoint,init_state,success\n\n"), task="push-t")
    with pytest.raises(ValueError, match="does not exist"):
        read_real_csv(tmp_path / "missing.csv")
    # a UTF-8 byte-order mark and upper-case, padded header names are accepted
    p = tmp_path / "bom.csv"
    p.write_bytes("\ufeffPolicy, Checkpoint ,INIT_STATE,success\na,,0,yes\n".encode())
    assert read_real_csv(p, task="push-t")[0].success is True


def test_task_is_given_or_inferred_never_defaulted(tmp_path, capsys):
    plain = _write(tmp_path, "policy,checkpoint,init_state,success\na,,0,1\n", "plain.csv")
    with pytest.raises(ValueError, match="no task column and no --task: give --task TASK \\(one of .*push-t"):
        read_real_csv(plain)
    # inferred from the task column (one task on every row), and the CLI says where it came from
    tagged = _write(tmp_path, "policy,checkpoint,init_state,success,task\na,,0,1,rope-routing\n"
                              "a,,1,0,rope-routing\n", "tagged.csv")
    assert [r.task for r in read_real_csv(tagged)] == ["rope-routing"] * 2
    db = tmp_path / "t.sqlite"
    assert cli_main(["import-real", str(tagged), "--db", str(db)]) == 0
    assert "of task 'rope-routing' (from the CSV's task column)" in capsys.readouterr().out
    assert ResultsStore(db).run_protocol("real")["grid"]["n_states"] == 27
    # a row of another task, or an empty task cell without --task, is refused (nothing imported)
    mixed = _write(tmp_path, "policy,checkpoint,init_state,success,task\na,,0,1,rope-routing\n"
                             "a,,1,0,push-t\na,,2,0,\n", "mixed.csv")
    with pytest.raises(ValueError) as info:
        read_real_csv(mixed)
    assert "row 3, column task: 'push-t', but this import is of task 'rope-routing'" in str(info.value)
    assert "row 4, column task: empty, and no --task given" in str(info.value)
    with pytest.raises(ValueError, match="row 2, column task: 'rope-routing', but this import is of task"):
        read_real_csv(tagged, task="push-t")
    with pytest.raises(ValueError, match="unknown task 'nope'"):
        import_real_csv(tagged, ResultsStore(db), run_id="x", task="nope")


def test_index_map_and_final_metrics(tmp_path):
    from twinbench.evaluation.grids import read_index_map

    # the earlier push-T cell's order: the study's state i was our (i // 4) * 4 + [2, 3, 0, 1][i % 4]
    old = {i: (i // 4) * 4 + [2, 3, 0, 1][i % 4] for i in range(16)}
    csv_map = _write(tmp_path, "study_index,init_state\n" + "".join(f"{k},{v}\n" for k, v in old.items()),
                     "map.csv")
    json_map = tmp_path / "map.json"
    json_map.write_text(json.dumps([old[i] for i in range(16)]))
    assert read_index_map(csv_map, 16) == old == read_index_map(json_map, 16)
    text = "policy,checkpoint,init_state,success,final_msd\nact,,0,1,0.0012\nact,,5,0,0.0021\n"
    store = ResultsStore(tmp_path / "r.sqlite")
    recs = import_real_csv(_write(tmp_path, text), store, task="push-t", index_map=csv_map)
    assert [(r.init_state, r.metrics["study_index"]) for r in recs] == [(2, 0), (7, 5)]
    assert [r.metrics["final"] for r in recs] == [{"msd": 0.0012}, {"msd": 0.0021}]  # near miss vs success
    assert store.run_protocol("real")["index_map"]["5"] == 7
    for bad, needle in (({"0": 16}, "must be <= 15"), ({"0": 1, "1": 1}, "image of several"),
                        ({"a": 1}, "'a' is not an integer")):
        json_map.write_text(json.dumps(bad))
        with pytest.raises(ValueError, match=needle):
            read_index_map(json_map, 16)
    json_map.write_text(json.dumps({"0": 3}))
    with pytest.raises(ValueError, match="row 3, column init_state: the index map: index 5 is not in"):
        import_real_csv(_write(tmp_path, text), store, run_id="r2", task="push-t", index_map=json_map)
    with pytest.raises(ValueError, match="column final_msd: 'x' is not a number"):
        read_real_csv(_write(tmp_path, "policy,checkpoint,init_state,success,final_msd\na,,0,1,x\n"),
                      task="push-t")


def test_cli_import_real(tmp_path, capsys):
    db = tmp_path / "cli.sqlite"
    path = _write(tmp_path, GOOD)
    assert cli_main(["import-real", str(path), "--db", str(db), "--run-id", "lab", "--task", "push-t"]) == 0
    assert "imported 5 real episodes (3 successes)" in capsys.readouterr().out
    assert len(ResultsStore(db).episodes("lab", domain="real")) == 5
    bad = _write(tmp_path, "policy,checkpoint,init_state,success\na,,0,perhaps\n", "bad.csv")
    assert cli_main(["import-real", str(bad), "--db", str(db), "--task", "push-t"]) == 2
    assert "bad.csv row 2, column success: 'perhaps'" in capsys.readouterr().err
