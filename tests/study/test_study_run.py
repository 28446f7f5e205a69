"""A tiny study end to end (slow): the hidden real workcell, perception policies calibrated on it, real
rollouts and two stand-in twins through the runner and one store, metrics and the study page. The
reconstruction itself is tested in test_reconstruct; here the twins are the real workcell itself (a
perfect twin: its outcomes must equal the real ones) and the task's fast cell (a naive twin). Fast: the
command's checks."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twinbench.cli import main as cli_main


def test_study_evaluate_needs_the_study_folder(tmp_path, capsys):
    assert cli_main(["study", "evaluate", str(tmp_path)]) == 2
    assert "needs real/world" in capsys.readouterr().err
    assert cli_main(["study", "run", "--out", str(tmp_path), "--size", "huge"]) == 2
    assert "study size 'huge' (--size)" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.timeout(2400)  # 9 episodes of 90 steps (real workcell and two twins): > 10 min on 2 busy cores
def test_tiny_study_end_to_end(tmp_path, monkeypatch):
    from twinbench.evaluation.store import ResultsStore
    from twinbench.policies import spec as spec_module
    from twinbench.study import evaluate as E
    from twinbench.study.real import make_real
    from twinbench.study.report import write_study_report
    from twinbench.tasks import get_task
    from twinbench.twin.files import save_twin

    real = make_real("push-t", 0, tmp_path / "real", "small")
    cell = get_task("push-t").task_cls().default_twin("fast")
    save_twin(cell, tmp_path / "twins" / "cell")
    twins = {"perfect": real / "world", "cell": tmp_path / "twins" / "cell"}
    tiny = E.StudySize((0,), 3.0, 2)  # without real_again, which the call below asks for (--real-again)
    monkeypatch.setattr(spec_module, "POLICY_KINDS", dict(spec_module.POLICY_KINDS))  # evaluate adds perceive
    policies = E.make_policies("push-t", real / "world", tmp_path / "policies", tiny, None,
                               names=("p0-clean", "p5-noise4cm", "p7-noise8cm"))
    assert len(policies) == 3 and (tmp_path / "policies" / "calibration.json").is_file()
    E.run_evaluations("push-t", real / "world", twins, policies, tmp_path, tiny, workers=1,  # entry point
                      real_again=True)
    doc = E.write_study_json(tmp_path, "push-t", tiny, list(twins), {"evaluate": 1.0})
    assert json.loads((tmp_path / "study.json").read_text()) == doc

    store = ResultsStore(tmp_path / "results" / "results.sqlite")
    real_eps = store.episodes(E.REAL, domain="real")
    assert len(real_eps) == 3 and all(r.status == "ok" for r in real_eps)
    for row in doc["variants"]:  # the table's rates are the store's
        sim_eps = {(r.policy, r.init_state): r.success for r in store.episodes(E.twin_run_id(row["variant"]))}
        for d in row["policies"]:
            assert d["sim"] == float(sim_eps[(d["policy"], 0)]) and d["n_sim"] == d["n_real"] == 1
            assert d["real"] == float(next(r.success for r in real_eps if r.policy == d["policy"]))
    perfect = doc["variants"][0]
    assert perfect["mmrv"]["value"] == 0.0  # the same world and seeds: the same outcomes
    assert all(d["sim"] == d["real"] for d in perfect["policies"])
    assert perfect["replay"]["accuracy"] == 1.0 and perfect["replay"]["excluded"] == 0  # same world: exact
    assert np.isfinite(doc["variants"][1]["mmrv"]["value"])
    # the real workcell again with every episode seed offset: the same episodes otherwise, in the table
    again = store.episodes(E.REAL_AGAIN)
    assert sorted((r.policy, r.init_state, r.seed) for r in again) == sorted(
        (r.policy, r.init_state, r.seed + E.AGAIN_SEED) for r in real_eps)
    assert doc["real_again"]["n_episodes"] == {"sim": 3, "real": 3}

    page = write_study_report(tmp_path, doc, twins=twins).read_text()
    assert "real | perfect" in page and "real | cell" in page
