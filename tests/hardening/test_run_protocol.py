"""The run protocol names the twin's content hash (a twin directory's files, or the TwinSpec a built-in cell
builds), so a run evaluated on a twin that changed since is refused on resume instead of mixing two twins'
outcomes (issue 25)."""

from __future__ import annotations

import json
import shutil

import pytest

from twinbench.cli import main as cli
from twinbench.evaluation.store import ResultsStore
from twinbench.twin import save_twin
from twinbench.twin.cells import push_t_cell
from twinbench.twin.files import twin_dir_hash


@pytest.fixture(scope="module")
def twin_dir(tmp_path_factory):
    return save_twin(push_t_cell("fast"), tmp_path_factory.mktemp("twin") / "t").parent


def _edit_friction(folder, value):
    doc = json.loads((folder / "twin.json").read_text())
    doc["sim"]["ground_friction"] = value
    (folder / "twin.json").write_text(json.dumps(doc))


def test_the_hash_follows_the_content_not_the_folder(twin_dir, tmp_path):
    copy = shutil.copytree(twin_dir, tmp_path / "elsewhere")
    assert twin_dir_hash(copy) == twin_dir_hash(twin_dir)
    _edit_friction(copy, 0.9)
    changed = twin_dir_hash(copy)
    assert changed != twin_dir_hash(twin_dir)
    _edit_friction(copy, json.loads((twin_dir / "twin.json").read_text())["sim"]["ground_friction"])
    (copy / "notes.txt").write_text("x")  # any file of the directory counts
    assert twin_dir_hash(copy) not in (changed, twin_dir_hash(twin_dir))


def _eval(folder, db, out):
    return ["eval", "--twin", str(folder), "--run-id", "R", "--task", "push-t", "--episodes", "grid:0",
            "--policy", "remote:ws://127.0.0.1:9", "--policy-timeout", "1", "--db", str(db),
            "--output-dir", str(out)]


def test_resuming_a_run_on_a_changed_twin_is_refused(twin_dir, tmp_path, capsys):
    folder = shutil.copytree(twin_dir, tmp_path / "twin")
    db = tmp_path / "r.sqlite"
    ResultsStore(db).start_run("R", "push-t", {"task": "push-t", "twin_hash": twin_dir_hash(folder)})
    _edit_friction(folder, 0.9)
    assert cli(_eval(folder, db, tmp_path / "out")) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "its files have changed since" in err[0] and "new --run-id" in err[0], err
    assert not (tmp_path / "out").exists()  # refused before any episode ran


@pytest.mark.slow
def test_the_stored_protocol_names_the_twin_hash_and_a_changed_twin_is_refused(twin_dir, tmp_path, capsys):
    folder = shutil.copytree(twin_dir, tmp_path / "twin")
    db = tmp_path / "r.sqlite"
    cli(_eval(folder, db, tmp_path / "out"))  # one episode (a policy_error: no server), the run is stored
    assert ResultsStore(db).run_protocol("R")["twin_hash"] == twin_dir_hash(folder)
    assert cli(_eval(folder, db, tmp_path / "out")) in (0, 1)  # unchanged: resumes (nothing left to run)
    _edit_friction(folder, 0.9)
    capsys.readouterr()
    assert cli(_eval(folder, db, tmp_path / "out")) == 2
    assert "its files have changed since" in capsys.readouterr().err


class _Ran(Exception):
    """Raised by the stand-in for the episode runner: the protocol was accepted and stored."""


def _no_episodes(*args, **kwargs):
    raise _Ran


def _friction(monkeypatch, value):
    """The push-T cell as a code change would make it: another ground friction."""
    import dataclasses

    import twinbench.twin.cells as cells

    real = cells.push_t_cell

    def changed(*args, **kwargs):
        spec = real(*args, **kwargs)
        return dataclasses.replace(spec, sim=dataclasses.replace(spec.sim, ground_friction=value))

    monkeypatch.setattr(cells, "push_t_cell", changed)


def test_a_built_in_cell_is_identified_by_its_content(tmp_path, monkeypatch, capsys):
    import twinbench.evaluation.runner as runner
    from twinbench.env import resolve_task_twin
    from twinbench.errors import InputError
    from twinbench.twin.files import twin_spec_hash

    monkeypatch.setattr(runner, "run_local", _no_episodes)
    store = ResultsStore(tmp_path / "r.sqlite")
    args = ("push-t", ["expert"], "grid:0", 0, "R", store)
    kw = {"output_dir": tmp_path / "out", "env_kwargs": {"preset": "fast"}}
    with pytest.raises(_Ran):
        runner.evaluate(*args, **kw)
    stored = store.run_protocol("R")["twin_hash"]
    assert stored == twin_spec_hash(resolve_task_twin("push-t", None, "fast", None, {})[1])
    assert stored != twin_spec_hash(resolve_task_twin("push-t", None, "reference", None, {})[1])
    with pytest.raises(_Ran):  # the same cell: the run resumes
        runner.evaluate(*args, **kw)
    _friction(monkeypatch, 0.77)
    with pytest.raises(InputError, match="built-in cell .* the cell the code builds has changed since"):
        runner.evaluate(*args, **kw)
    argv = ["eval", "--run-id", "R", "--task", "push-t", "--policy", "expert", "--episodes", "grid:0",
            "--workers", "0", "--env-kwargs", '{"preset": "fast"}', "--db", str(tmp_path / "r.sqlite"),
            "--output-dir", str(tmp_path / "out")]
    capsys.readouterr()
    assert cli(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has changed since" in err[0] and "new --run-id" in err[0], err


def test_a_run_resumes_on_its_twin_moved_elsewhere_and_a_policy_file_moved_with_it(twin_dir, tmp_path,
                                                                                   monkeypatch):
    """A moved study or results folder: the same twin (same content hash) at another path, and a policy
    spec whose file moved (the same label), resume the run (the protocol takes the new path; no policy is
    counted as added); other settings that differ, or a changed twin at the new path, are still refused.
    Before, the path alone refused the resume ("different protocol keys ['env_kwargs', ...]")."""
    import twinbench.evaluation.runner as runner
    from twinbench.errors import InputError

    monkeypatch.setattr(runner, "run_local", _no_episodes)
    store = ResultsStore(tmp_path / "r.sqlite")
    first = shutil.copytree(twin_dir, tmp_path / "a" / "twin")
    (tmp_path / "a" / "p.json").write_text("{}")
    logs = []

    def run(folder, policies, **extra):
        with pytest.raises(_Ran):
            runner.evaluate("push-t", policies, "grid:0", 0, "R", store, output_dir=tmp_path / "out",
                            env_kwargs={"twin": str(folder), "cameras": "front", **extra}, log=logs.append)

    run(first, ["mine=remote:ws://127.0.0.1:9?io=" + str(tmp_path / "a" / "p.json")])
    moved = shutil.move(tmp_path / "a", tmp_path / "b")
    second = tmp_path / "b" / "twin"
    logs.clear()
    run(second, ["mine=remote:ws://127.0.0.1:9?io=" + str(tmp_path / "b" / "p.json")])
    assert store.run_protocol("R")["env_kwargs"]["twin"] == str(second) and moved
    assert not [line for line in logs if "adding" in line]
    said = f"run 'R': its twin is at {second} now (the same files as where the run started: {first})"
    assert said in logs[0]
    with pytest.raises(InputError, match=r"different protocol keys \['env_kwargs'"):
        runner.evaluate("push-t", ["mine=remote:ws://127.0.0.1:9"], "grid:0", 0, "R", store,
                        output_dir=tmp_path / "out", env_kwargs={"twin": str(second), "cameras": ""})
    _edit_friction(second, 0.9)
    with pytest.raises(InputError, match="its files have changed since"):
        run(second, ["mine=remote:ws://127.0.0.1:9"])
