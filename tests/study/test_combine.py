"""`twinbench study combine`: several studies' study.json read as one table (twinbench.study.combine), with
known answers from the rates themselves."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from twinbench.cli import main as cli_main
from twinbench.errors import InputError
from twinbench.evaluation import metrics
from twinbench.evaluation.report_browser import CHROMIUM, check_page
from twinbench.study import combine as C
from twinbench.study import evaluate as E
from twinbench.twin.files import twin_dir_hash


def _outcomes(rates: dict[str, float], n: int = 4) -> dict:
    return {(p, f"{p}.json"): [1] * round(r * n) + [0] * (n - round(r * n)) for p, r in rates.items()}


def _doc(real: dict, twins: dict, again: dict | None = None, *, size="medium", seed=None, world=None) -> dict:
    """A study.json as `write_study_json` makes its rows (E._agreement), from per-policy rates."""
    real_o = _outcomes(real)
    return {"task": "push-t", "size": size, "seed": seed, "real_world": world,
            "variants": [E._agreement(v, _outcomes(r), real_o) for v, r in twins.items()],
            "real_again": E._agreement("real again", _outcomes(again), real_o) if again else None}


REAL_A = {"a": 0.0, "b": 0.25, "c": 0.75, "d": 1.0}
REAL_B = {"a": 0.25, "b": 0.5, "c": 0.5, "d": 0.75, "e": 0.0}
FULL_B = {"a": 0.5, "b": 0.25, "c": 0.75, "d": 1.0, "e": 0.0}


@pytest.fixture
def two(tmp_path):
    """Workcell A: `full` equals the real rates (r 1, MMRV 0: both aims); B: `full` swaps two policies.
    The user's twin `mine` exists only in A."""
    docs = {"A": _doc(REAL_A, {"full": REAL_A, "mine": REAL_A}, {"a": 0.25, "b": 0.0, "c": 1.0, "d": 0.75},
                      seed=0, world="hash-a"),
            "B": _doc(REAL_B, {"full": FULL_B}, REAL_B, seed=1, world="hash-b")}
    for name, doc in docs.items():
        (tmp_path / name).mkdir()
        (tmp_path / name / "study.json").write_text(json.dumps(doc))
    return tmp_path


def test_pooled_within_and_mean_mmrv(two):
    (task,) = C.combine_studies([C.load_study(two / "A"), C.load_study(two / "B" / "study.json")])
    assert task["task"] == "push-t" and [s["study"] for s in task["studies"]] == ["A", "B"]
    assert [v["variant"] for v in task["variants"]] == ["full", "real again"]
    assert task["missing"] == {"mine": ["B"]}
    full = task["variants"][0]
    sim = np.array([*REAL_A.values(), *FULL_B.values()])
    real = np.array([*REAL_A.values(), *REAL_B.values()])
    assert full["points"] == 9 and full["workcells"] == 2
    assert full["pooled"]["r"] == pytest.approx(np.corrcoef(sim, real)[0, 1])
    assert full["pooled"]["low"] == pytest.approx(metrics.pearson(sim=sim, real=real).low)
    # within: each workcell's mean rate taken out of sim and real; the interval with 9 - 3 - 1 degrees
    g = np.array([0] * 4 + [1] * 5)
    cs = sim - np.where(g == 0, sim[:4].mean(), sim[4:].mean())
    cr = real - np.where(g == 0, real[:4].mean(), real[4:].mean())
    r_in = np.corrcoef(cs, cr)[0, 1]
    half = stats.norm.ppf(0.975) / np.sqrt(9 - 3 - 1)
    assert full["within"]["r"] == pytest.approx(r_in)
    assert full["within"]["high"] == pytest.approx(np.tanh(np.arctanh(r_in) + half))
    # MMRV: A 0; B: a (sim .5 > b's .25, real .25 < .5) is violated by 0.25 on both sides -> 0.5 / 5 = 0.1
    per = {p["study"]: p for p in full["per_workcell"]}
    assert per["A"]["mmrv"] == 0.0 and per["B"]["mmrv"] == pytest.approx(0.1)
    assert full["mmrv"]["value"] == pytest.approx(0.05)
    assert full["mmrv"]["low"] <= full["mmrv"]["high"]
    assert per["A"]["r"] == pytest.approx(1.0) and per["A"]["aims_met"] and not per["B"]["aims_met"]
    assert full["aims_met"] == 1 and per["B"]["seed"] == 1
    assert per["B"]["sim_successes"] == 10 and per["B"]["real_successes"] == 8
    table = C.format_combined([task])
    assert "| push-t | full | 2 (9) | " in table and "| 1 of 2 |" in table
    assert "1.00 / 0.000; " in table and "push-t: mine left out (not in B)" in table


def test_a_workcell_without_a_real_order_is_left_out_of_the_mean_mmrv(two):
    """Workcell Z: every policy fails for real, so its MMRV is 0 whatever the twin does (here the twin
    succeeds with two of them) and its r undefined: the mean MMRV is A's and B's, Z named; Z's points
    stay in the pooled r."""
    z = _doc({"a": 0.0, "b": 0.0, "c": 0.0}, {"full": {"a": 0.0, "b": 0.5, "c": 1.0}}, seed=4, world="hash-z")
    (two / "Z").mkdir()
    (two / "Z" / "study.json").write_text(json.dumps(z))
    with_z, = C.combine_studies([C.load_study(two / n) for n in ("A", "B", "Z")])
    without, = C.combine_studies([C.load_study(two / n) for n in ("A", "B")])
    full, base = with_z["variants"][0], without["variants"][0]
    per = {p["study"]: p for p in full["per_workcell"]}
    assert per["Z"]["mmrv"] == 0.0 and per["Z"]["r"] is None and not per["Z"]["aims_met"]
    assert full["mmrv"]["left_out"] == ["Z"] and full["mmrv"]["workcells"] == 2
    assert full["mmrv"]["value"] == pytest.approx(base["mmrv"]["value"]) == pytest.approx(0.05)  # not 0.1/3
    assert full["points"] == 12 and full["pooled"]["r"] != pytest.approx(base["pooled"]["r"])
    assert "in Z every real success rate is the same" in C.format_combined([with_z])
    assert C.flat_note(without) is None and "left_out" in base["mmrv"] and base["mmrv"]["left_out"] == []


def test_combine_refuses_what_would_mislead(two, tmp_path):
    a = C.load_study(two / "A")
    with pytest.raises(InputError, match="A and copy are studies of the same hidden workcell"):
        C.combine_studies([a, ("copy", dict(a[1]))])
    # without a recorded real workcell (an older study.json, its folder gone), the seed tells
    no_world = {**a[1], "real_world": None}
    with pytest.raises(InputError, match="the same seed"):
        C.combine_studies([("x", no_world), ("y", dict(no_world))])
    # a variant whose twin run has no episode yet counts as missing there, not as a workcell without points
    empty = _doc(REAL_B, {"full": REAL_B, "mine": {}}, seed=7, world="hash-d")
    (task,) = C.combine_studies([a, ("E", empty)])
    assert task["missing"] == {"mine": ["E"], "real again": ["E"]}
    assert [v["variant"] for v in task["variants"]] == ["full"] and task["variants"][0]["points"] == 9
    small = _doc(REAL_A, {"full": REAL_A}, size="small", seed=5, world="hash-c")
    with pytest.raises(InputError, match=r"sizes \['medium', 'small'\].*one size"):
        C.combine_studies([a, ("S", small)])
    with pytest.raises(InputError, match="no studies"):
        C.combine_studies([])
    with pytest.raises(InputError, match="no study.json"):
        C.load_study(tmp_path / "nowhere")
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "study.json").write_text("{not json")
    with pytest.raises(InputError, match="bad/study.json: not readable as JSON"):
        C.load_study(tmp_path / "bad")
    (tmp_path / "bad" / "study.json").write_text(json.dumps({"task": "push-t"}))
    with pytest.raises(InputError, match="not a study.json"):
        C.load_study(tmp_path / "bad")


def test_a_study_without_its_recorded_workcell_reads_it_off_the_folder(two):
    world = two / "A" / "real" / "world"
    world.mkdir(parents=True)
    (world / "twin.json").write_text('{"name": "hidden"}')
    doc = json.loads((two / "A" / "study.json").read_text())
    (two / "A" / "study.json").write_text(json.dumps({**doc, "real_world": None}))
    assert C.load_study(two / "A")[1]["real_world"] == twin_dir_hash(world) == E.real_world_hash(two / "A")
    assert E.real_world_hash(two / "B") is None


def test_cli_prints_the_table_and_writes_json_and_a_page(two, capsys):
    out = two / "summary"
    assert cli_main(["study", "combine", str(two / "A"), str(two / "B"), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| push-t | real again | 2 (9) | " in printed and f"wrote {out / 'combined.json'}" in printed
    (task,) = json.loads((out / "combined.json").read_text())
    full = task["variants"][0]
    assert full["pooled"]["r"] == pytest.approx(
        np.corrcoef([*REAL_A.values(), *FULL_B.values()], [*REAL_A.values(), *REAL_B.values()])[0, 1])
    assert full["points_by_workcell"][1] == {"sim": list(FULL_B.values()), "real": list(REAL_B.values())}
    text = (out / "combined.html").read_text()
    assert "push-t (medium): 2 workcells" in text and "A (seed 0), B (seed 1)" in text
    assert "<td>full</td><td>2 (9)</td>" in text and "<td>1 of 2</td>" in text
    assert "mine: left out, not in B" in text and "data:image/png;base64," in text
    if Path(CHROMIUM).exists():
        res = check_page(out / "combined.html")
        assert res.errors == []
        assert len(res.images) == 1 and res.images[0]["naturalWidth"] > 0  # the scatter
    assert cli_main(["study", "combine", str(two / "A"), str(two / "A")]) == 2
    assert "same hidden workcell" in capsys.readouterr().err
    assert cli_main(["study", "combine", str(two / "A"), "--out", str(two / "A" / "study.json")]) == 2
    assert "give a folder" in capsys.readouterr().err
