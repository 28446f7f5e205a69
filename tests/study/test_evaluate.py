"""Study metrics from the results store (twinbench.study.evaluate) with known answers, study.json, the study
page (and its rendering in headless Chromium)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from twinbench.evaluation.report_browser import CHROMIUM, check_page
from twinbench.evaluation.store import EpisodeRecord, ResultsStore
from twinbench.study import evaluate as E

REAL_RATES = {"a": [0, 0, 0, 0], "b": [1, 0, 0, 0], "c": [1, 1, 1, 0], "d": [1, 1, 1, 1]}  # 0, .25, .75, 1


def _records(run_id: str, domain: str, rates: dict) -> list[EpisodeRecord]:
    return [EpisodeRecord(run_id, "push-t", p, f"{p}.json", None, i, i, domain, bool(s), "ok")
            for p, outcomes in rates.items() for i, s in enumerate(outcomes)]


@pytest.fixture
def study(tmp_path) -> Path:
    """A study folder whose store holds real outcomes, three twins (one that agrees: the same outcomes, one
    that ranks the policies backwards, one where every policy succeeds) and a second real evaluation."""
    store = ResultsStore(tmp_path / "results" / "results.sqlite")
    store.start_run_with_episodes(E.REAL, "push-t", {"task": "push-t"}, _records(E.REAL, "real", REAL_RATES))
    backwards = dict(zip(REAL_RATES, reversed(list(REAL_RATES.values())), strict=True))
    for variant, rates in (("full", REAL_RATES), ("no-color", backwards),
                           ("neither", {p: [1, 1, 1, 1] for p in REAL_RATES})):
        run = E.twin_run_id(variant)
        store.start_run_with_episodes(run, "push-t", {"task": "push-t"}, _records(run, "sim", rates))
    # replays in the twin "full": the real outcomes, with every replay a success -> TP 8, FP 8
    run = E.replay_run_id("full")
    store.start_run_with_episodes(run, "push-t", {"task": "push-t"}, _records(run, "real", REAL_RATES)
                                  + _records(run, "replay", {p: [1, 1, 1, 1] for p in REAL_RATES}))
    # the real workcell again (other seeds): a and b swap, c and d swap
    again = {"a": [0, 0, 0, 1], "b": [0, 0, 0, 0], "c": [1, 1, 1, 1], "d": [1, 1, 1, 0]}
    store.start_run_with_episodes(E.REAL_AGAIN, "push-t", {"task": "push-t"},
                                  _records(E.REAL_AGAIN, "sim", again))
    # an errored episode is left out of the rates, never counted as a failure
    store.record_episode(EpisodeRecord(E.twin_run_id("full"), "push-t", "a", "a.json", None, 9, 9, "sim",
                                       True, "sim_error"))
    return tmp_path


def test_metrics_from_the_store(study):
    store = ResultsStore(study / "results" / "results.sqlite")
    full, backwards, constant = E.study_table(store, ["full", "no-color", "neither"])
    assert full["n_policies"] == 4 and full["n_episodes"] == {"sim": 16, "real": 16}
    assert [d["real"] for d in full["policies"]] == [0.0, 0.25, 0.75, 1.0]
    assert full["pearson"]["r"] == pytest.approx(1.0) and full["mmrv"]["value"] == 0.0
    assert backwards["pearson"]["r"] == pytest.approx(-1.0)
    # MMRV: every pair is ranked the other way; max |R_i - R_j| per policy = 1, .75, .75, 1 -> mean 0.875
    assert backwards["mmrv"]["value"] == pytest.approx(0.875)
    assert backwards["mmrv"]["low"] <= 0.875 <= backwards["mmrv"]["high"]
    assert constant["pearson"]["r"] is None and "zero variance" in constant["pearson"]["why"]
    # every sim rate 1: a pair is violated where real ranks i above j; max |R_i - R_j| = 0, .25, .75, 1
    assert constant["mmrv"]["value"] == pytest.approx((0 + 0.25 + 0.75 + 1) / 4)
    assert full["replay"] == {"tp": 8, "fp": 8, "fn": 0, "tn": 0, "excluded": 0, "accuracy": 0.5}
    assert backwards["replay"] is None  # no replays in that twin
    again = E.real_again_metrics(store)  # rates .25, 0, 1, .75 against 0, .25, .75, 1
    assert again["variant"] == "real again" and again["n_episodes"] == {"sim": 16, "real": 16}
    assert again["pearson"]["r"] == pytest.approx(0.8)
    # two pairs flipped, each by 0.25 in real rate: every policy's worst violation is 0.25
    assert again["mmrv"]["value"] == pytest.approx(0.25) and "replay" not in again
    assert E.real_again_metrics(ResultsStore(study / "empty.sqlite")) is None


def test_rates_per_grid_state(study):
    """Episode i of each policy starts from grid state i: real rates per state .75, .5, .5, .25."""
    store = ResultsStore(study / "results" / "results.sqlite")
    full, backwards, constant = E.study_table(store, ["full", "no-color", "neither"])
    real = [0.75, 0.5, 0.5, 0.25]
    assert [d["init_state"] for d in full["states"]["rates"]] == [0, 1, 2, 3]
    assert [d["real"] for d in full["states"]["rates"]] == real
    assert [d["sim"] for d in full["states"]["rates"]] == real
    assert all(d["n_sim"] == d["n_real"] == 4 for d in full["states"]["rates"])
    assert full["states"]["pearson"]["r"] == pytest.approx(1.0)
    # the policies' outcomes swapped round: every policy ranked backwards, every state's rate right
    assert backwards["pearson"]["r"] == pytest.approx(-1.0)
    assert [d["sim"] for d in backwards["states"]["rates"]] == real
    assert backwards["states"]["pearson"]["r"] == pytest.approx(1.0)
    undefined = constant["states"]["pearson"]
    assert undefined["r"] is None and "zero variance" in undefined["why"]
    again = E.real_again_metrics(store)  # states: (0+0+1+1)/4 ... every state 0.5
    assert [d["sim"] for d in again["states"]["rates"]] == [0.5] * 4
    assert again["states"]["pearson"]["r"] is None


def test_study_json_table_and_page(study):
    # policy c as a behaviour-cloned checkpoint: its train.json joins study.json and the page
    ckpt = study / "bc" / "c.json"
    ckpt.mkdir(parents=True)
    (ckpt / "train.json").write_text(json.dumps({"demos": 8, "frames": 1200, "epochs": 40, "loss": 0.0123,
                                                 "train_seconds": 61.0}))
    training = E.training_records([f"c=cnn:{ckpt}", "d=expert"])
    assert training == [{"policy": "c", "checkpoint": "c.json", "arch": "cnn", "demos": 8, "frames": 1200,
                         "epochs": 40, "loss": 0.0123, "train_seconds": 61.0}]
    doc = E.write_study_json(study, "push-t", "small", ["full", "no-color", "neither"],
                             {"make-real": 1.0, "evaluate": 2.0},
                             {"training": training, "user_policies": ["d=perceive:mine.json"]})
    assert json.loads((study / "study.json").read_text()) == doc
    table = E.format_table(doc)
    assert "| push-t | full | 1.000 [1.00, 1.00] | 0.000 [0.000, " in table and "| 4 | 16 / 16 |" in table
    assert "| push-t | neither | undefined |" in table
    assert "| 0.50 (8/8/0/0) |" in table and table.count("| - |") == 3
    assert table.splitlines()[-1].startswith("| push-t | real again | 0.800 [")  # the yardstick, last
    assert E.no_real_order(doc) is None
    flat = json.loads(json.dumps(doc))  # every policy fails for real: no twin can be told apart by r / MMRV
    for row in flat["variants"]:
        for p in row["policies"]:
            p["real"] = 0.0
    assert E.format_table(flat).endswith("Every policy's real success rate is 0.000: with no real order to "
                                         "violate, every twin's MMRV is 0 and its r undefined here, so this "
                                         "workcell cannot rank twins (the twins' own rates still show which "
                                         "predict it); `study combine` leaves it out of the mean MMRV.")

    from twinbench.study.report import write_study_report

    page = write_study_report(study, doc, frames=False)
    text = page.read_text()
    assert "Sim vs real, per twin variant" in text and "0.875" in text and "stage" in text.lower()
    assert "0.50 (8 / 8 / 0 / 0)" in text
    # per grid state: real .75 (4 episodes), full and no-color the same, neither 1; r over the states
    assert "Success per grid state" in text
    assert "<td>0</td><td>0.75 (4)</td><td>0.75</td><td>0.75</td><td>1.00</td><td>0.50</td>" in text
    assert "<td>r over the states</td><td></td><td>1.000</td><td>1.000</td>" in text
    assert "<td>real again</td><td>0.800 [" in text and "evaluated a second time" in text
    # c: real 0.75, full 0.75 (the same outcomes), no-color 0.25 (b's, backwards), neither 1
    # per policy: d (the user's) real 1 in 4 episodes, full 1, no-color 0 (a's, backwards), neither 1, and
    # in the second real evaluation 0.75
    assert "Success per policy" in text
    assert ("<td>d (yours)</td><td>d.json</td><td>1.00 (4)</td><td>1.00</td><td>0.00</td><td>1.00</td>"
            "<td>0.75</td>") in text
    assert "<td>a</td><td>a.json</td><td>0.00 (4)</td>" in text
    assert "Behaviour-cloned checkpoints" in text
    assert ("<td>c</td><td>cnn</td><td>8</td><td>1200</td><td>40</td><td>0.0123</td><td>61</td><td>0.75</td>"
            "<td>0.75</td><td>0.25</td><td>1.00</td>") in text
    for variant in ("full", "no-color", "neither"):
        assert (study / "reports" / f"{variant}.html").is_file()
    if Path(CHROMIUM).exists():
        res = check_page(page)
        assert res.errors == []
        assert len(res.images) == 1 and res.images[0]["naturalWidth"] > 0  # the scatter, real again in it


def test_bad_size_is_refused():
    from twinbench.errors import InputError

    with pytest.raises(InputError, match=r"study size 'huge' \(--size\)"):
        E.study_size("huge")
    assert E.episodes_arg(E.study_size("small")) == "grid:0,9"


def test_a_study_resumes_its_runs_on_the_device_they_began_on(tmp_path):
    """--device reaches the runs' env_kwargs (left out on CPU, so older studies' runs resume as they are),
    and a run begun on one device is not resumed on another: refused before any episode runs."""
    from twinbench.errors import InputError

    small = E.study_size("small")
    assert "device" not in E.env_kwargs(tmp_path, small)
    assert E.env_kwargs(tmp_path, small, "cuda:1")["device"] == "cuda:1"
    store = ResultsStore(tmp_path / "results" / "results.sqlite")
    store.start_run(E.replay_run_id("full"), "push-t", {"task": "push-t", "env_kwargs": {"device": "cuda"}})
    E.check_run_devices(store, [E.twin_run_id("full"), E.replay_run_id("full")], "cuda")
    with pytest.raises(InputError, match="run 'replay-full' was started with --device cuda; resume the study "
                                         "with --device cuda"):
        E.run_evaluations("push-t", tmp_path / "real", {"full": tmp_path / "full"}, ["expert"], tmp_path,
                          "small", device="cpu")
    assert store.episodes(E.REAL_ROLLOUTS) == []  # nothing ran


def test_a_twin_that_differs_only_in_appearance_takes_the_replays_of_its_physics_twin(tmp_path):
    """`no-color` (the fast cell with a colour map and another name) has `full`'s physics: its replay run is
    `full`'s records, copied with a protocol naming the source, and no replay is run; a replay run that
    exists already is left to resume as it was started."""
    import dataclasses

    from twinbench.gaussians.colormap import identity_color_map
    from twinbench.tasks import get_task
    from twinbench.twin import ColorMap, save_twin

    cell = get_task("push-t").task_cls().default_twin("fast")
    cmap = identity_color_map(2)
    cmap[0, 0] = 0.1
    tinted = dataclasses.replace(cell, name="tinted", background_color_map=ColorMap(2, cmap))
    twins = {"full": tmp_path / "full", "no-color": tmp_path / "no-color"}
    save_twin(cell, twins["full"])
    save_twin(tinted, twins["no-color"])
    store = ResultsStore(tmp_path / "results.sqlite")
    store.start_run_with_episodes(E.REAL_ROLLOUTS, "push-t", {"task": "push-t"},
                                  _records(E.REAL_ROLLOUTS, "sim", REAL_RATES))
    run = E.replay_run_id("full")  # every replay in `full` done: replay_in_twin has nothing to run
    full = _records(run, "real", REAL_RATES) + _records(run, "replay", {p: [0, 1, 0, 1] for p in REAL_RATES})
    before = {"task": "push-t", "kind": "replay", "env_kwargs": {"twin": "/old/full"}, "twin_hash": "h"}
    store.start_run_with_episodes(run, "push-t", before, full)
    logs = []
    E.replay_in_twins("push-t", store, tmp_path, twins, E.study_size("small"), logs.append)
    copied = store.episodes(E.replay_run_id("no-color"))
    assert [dataclasses.replace(r, run_id=run) for r in copied] == store.episodes(run)
    assert store.run_protocol(E.replay_run_id("no-color"))["copied_from"] == run
    assert any("only in appearance" in m for m in logs)
    # the source gains replays (a study extended with a policy), after the study folder moved (its twin
    # at another path, as replay_episodes then records it): the copy follows, nothing is run
    extra = {"e": [1, 0]}
    store.start_run_with_episodes(run, "push-t", {**before, "env_kwargs": {"twin": "/new/full"}},
                                  _records(run, "real", extra) + _records(run, "replay", extra),
                                  grow=("env_kwargs",))
    store.record_episodes(_records(E.REAL_ROLLOUTS, "sim", extra))
    E.replay_in_twins("push-t", store, tmp_path, twins, E.study_size("small"), logs.append)
    assert len(store.episodes(E.replay_run_id("no-color"))) == 36
    assert store.run_protocol(E.replay_run_id("no-color"))["env_kwargs"] == {"twin": "/new/full"}
    # a replay run that was run, not copied (an older study), is resumed as it is: here complete, nothing
    # runs and nothing is copied over it
    other = ResultsStore(tmp_path / "other.sqlite")
    other.start_run_with_episodes(E.REAL_ROLLOUTS, "push-t", {"task": "push-t"},
                                  _records(E.REAL_ROLLOUTS, "sim", REAL_RATES))
    other.start_run_with_episodes(run, "push-t", {"task": "push-t", "kind": "replay"}, full)
    own = E.replay_run_id("no-color")
    kept = _records(own, "real", REAL_RATES) + _records(own, "replay", REAL_RATES)
    other.start_run_with_episodes(own, "push-t", {"task": "push-t", "kind": "replay"}, kept)
    logs.clear()
    E.replay_in_twins("push-t", other, tmp_path, twins, E.study_size("small"), logs.append)
    assert logs == [] and "copied_from" not in other.run_protocol(own)
    assert [r.success for r in other.episodes(own, domain="replay")] == [
        bool(v) for p in sorted(REAL_RATES) for v in REAL_RATES[p]]  # its own outcomes, not full's
