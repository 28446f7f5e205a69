"""System identification's files (twinbench.construct.sysid_io, sysid_report) and `twinbench sysid`: the
input directory round trip and its errors, the identified object directory, the report, the command."""

from __future__ import annotations

import json

import numpy as np
import pytest

from twinbench.commands.sysid import SysIdConfig, main
from twinbench.construct.sysid_io import load_sysid_data, save_sysid_data, write_object_dir
from twinbench.construct.sysid_report import write_report
from twinbench.construct.sysid_synthetic import synthetic_case
from twinbench.physics import SimParams
from twinbench.physics.sysid import AdamConfig, CMAConfig, FitConfig, GlobalParams, identify
from twinbench.physics.sysid_data import SysIdFormatError

SUBSTEPS = 40  # as tests/physics/test_sysid.py: 40 substeps per 30 Hz frame, stiffness within [50, 1e4]
SEARCH = ("spring_Y", "control_radius", "control_max_neighbors", "ground_restitution", "ground_friction",
          "drag_damping", "dashpot_damping")


@pytest.fixture(scope="module")
def identified():
    """A short rope identified by the three stages (80 CMA-ES evaluations, 10 Adam epochs, stage 3's default
    budget), the last 2 training frames held out from fitting to choose the stage."""
    data, truth = synthetic_case("rope", frames=12, validation_frames=3, seed=0)
    cfg = FitConfig(dt=1.0 / (30 * SUBSTEPS), substeps=SUBSTEPS, progress=False,
                    initial=GlobalParams(spring_Y=1000.0, control_radius=0.02, control_max_neighbors=8),
                    cma=CMAConfig(budget=80, search=SEARCH, ranges=("spring_Y=100:10000",), seed=0),
                    adam=AdamConfig(epochs=10, lr=0.02, y_min=50.0, y_max=1e4), select_frames=0.2)
    return data, truth, identify(data, cfg, log=lambda _msg: None)


def test_save_load_round_trip_and_file_errors(sysid_small, tmp_path):
    path = save_sysid_data(sysid_small, tmp_path / "case")
    back = load_sysid_data(tmp_path / "case")
    for key, val in sysid_small.arrays().items():
        np.testing.assert_array_equal(getattr(back, key), val)
    assert (back.fps, back.validation_frames, back.name) == (30.0, 2, "rope")
    assert load_sysid_data(path).num_frames == 6

    meta = json.loads(path.read_text())
    for bad, words in [({"format": "x"}, "field 'format'"), ({"version": 2}, "field 'version'"),
                       ({"arrays": "../data.npz"}, "inside the directory"), ({"fps": "30"}, "field 'fps'"),
                       ({"extra": 1}, "unknown field")]:
        path.write_text(json.dumps(meta | bad))
        with pytest.raises(SysIdFormatError, match=words):
            load_sysid_data(path)
    path.write_text("{not json")
    with pytest.raises(SysIdFormatError, match="not valid JSON"):
        load_sysid_data(path)
    path.write_text(json.dumps(meta))
    arrays = sysid_small.arrays()
    np.savez(tmp_path / "case" / "data.npz", **{k: v for k, v in arrays.items() if k != "controls"})
    with pytest.raises(SysIdFormatError, match=r"missing array\(s\) \['controls'\]"):
        load_sysid_data(path)
    np.savez(tmp_path / "case" / "data.npz", **arrays, springs=np.array([{"a": 1}], dtype=object))
    with pytest.raises(SysIdFormatError, match="pickled Python objects"):
        load_sysid_data(path)
    with pytest.raises(SysIdFormatError, match="not found"):
        load_sysid_data(tmp_path / "nowhere")


def test_outputs_object_directory_and_report(identified, tmp_path):
    from twinbench.physics import ModelBuilder
    from twinbench.twin import load_object

    data, truth, result = identified
    path = write_object_dir(result, data, tmp_path / "rope")
    meta = json.loads(path.read_text())
    assert meta["format"] == "twinbench-object" and meta["version"] == 2  # twin files version 2 (f09df4a)
    assert meta["object"]["springs"] == "explicit" and meta["object"]["spring_Y"] is None
    obj, sim = load_object(tmp_path / "rope")
    n = result.model.num_object_springs
    assert obj.name == "rope" and np.allclose(obj.rest_pose, np.eye(4))
    np.testing.assert_allclose(obj.particles, data.particles, atol=1e-7)
    np.testing.assert_array_equal(obj.springs, truth["springs"])
    np.testing.assert_allclose(obj.spring_Y, np.exp(result.log_y[:n].astype(np.float64)))
    np.testing.assert_array_equal(obj.mass, np.ones(data.num_particles))
    assert sim["dashpot_damping"] == pytest.approx(result.params.dashpot_damping)
    assert sim["ground_friction"] == pytest.approx(result.params.ground_friction)
    assert sim["substeps"] == SUBSTEPS
    # the loaded object builds (as build_twin does) into the identified object's springs and stiffness
    b = ModelBuilder(SimParams(**{**sim, "gravity": tuple(sim["gravity"])}))
    b.add_body(obj.particles, springs=obj.springs, rest_lengths=obj.rest_lengths, spring_Y=obj.spring_Y,
               mass=obj.mass)
    twin_model = b.finalize()
    np.testing.assert_array_equal(twin_model.springs_np, result.model.springs_np[:n])
    np.testing.assert_allclose(twin_model.rest_lengths_np, result.model.rest_lengths_np[:n])
    np.testing.assert_allclose(twin_model.log_y_np, result.log_y[:n], atol=1e-5)

    jpath, ppath = write_report(result, data, tmp_path)
    rep = json.loads(jpath.read_text())
    assert rep["evaluations"]["final"]["val_error_m"] == pytest.approx(result.evals["final"].val_error)
    assert len(rep["evaluations"]["final"]["per_frame_error_m"]) == data.num_frames
    # every stage-1 evaluation (CMA-ES stops after 3 generations without a 1 % better loss, at most 80)
    assert rep["stage1_history"] == json.loads(json.dumps(result.stage1_history))
    assert 20 <= len(rep["stage1_history"]) <= 80
    assert rep["stages"] == {"stage1": True, "stage2": True, "stage3": True, "stage4": False}
    assert rep["stage3_history"] == json.loads(json.dumps(result.stage3_history)) and rep["stage3_history"]
    assert rep["stiffness_fit"]["per"] == "region" and sum(rep["stiffness_fit"]["springs"]) == n
    assert rep["global_params"]["spring_Y"] == pytest.approx(result.params.spring_Y)
    # the starting guesses from the data and the stage kept by the selection frames (not the validation ones)
    assert set(rep["guesses"]) == {"spring_Y", "ground_friction", "ground_restitution"}
    assert all(isinstance(g["from"], str) and isinstance(g["used"], bool) for g in rep["guesses"].values())
    sel = rep["selection"]
    errs, order = sel["errors_m"], ["initial", "stage1", "stage2", "stage3"]
    assert sel["frames"] == [7, 8] and list(errs) == order
    # the kept stage beats every later one by 2 % on the selection frames and is within 2 % of the best
    assert all(errs[sel["kept"]] < 0.98 * errs[s] for s in order[order.index(sel["kept"]) + 1:])
    assert errs[sel["kept"]] <= min(errs.values()) / 0.98
    assert rep["evaluations"]["final"] == rep["evaluations"][sel["kept"]]
    assert ppath.stat().st_size > 10_000 and ppath.read_bytes()[:4] == b"\x89PNG"


def test_cli_help_and_end_to_end(sysid_small, tmp_path, capsys):
    from twinbench.cli import main as cli_main

    with pytest.raises(SystemExit) as ex:
        cli_main(["sysid", "--help"])
    assert ex.value.code == 0
    assert "--cma.budget" in capsys.readouterr().out

    save_sysid_data(sysid_small, tmp_path / "case")
    # every applicable global parameter searched (spring and control rules included), tiny budgets
    rc = cli_main(["sysid", "--data", str(tmp_path / "case"), "--out-dir", str(tmp_path / "out"),
                   "--substeps", str(SUBSTEPS), "--dt", str(1.0 / (30 * SUBSTEPS)), "--no-progress",
                   "--initial.spring-Y", "1000", "--cma.budget", "8", "--cma.ranges", "spring_Y=100:10000",
                   "--adam.epochs", "1", "--adam.y-min", "50", "--adam.y-max", "1e4", "--stage4",
                   "--stage4-budget", "6", "--rounds", "2"])
    assert rc == 0
    assert "stiffness regions constrained by the motion" in capsys.readouterr().err
    rep = json.loads((tmp_path / "out" / "sysid_report.json").read_text())
    rows = rep["region_identifiability"]["regions"]  # per stiffness region; an unbounded std is null
    assert rows and all(r["std"] is None or r["std"] > 0 for r in rows)
    # stage 1 searched each spring set of the radius rule (--cma.topologies), each within the budget
    from twinbench.physics.sysid import parse_ranges, rule_topologies

    h1 = rep["stage1_history"]
    sets = {r["params"]["spring_radius"] for r in h1[1:]}
    assert [r["evaluation"] for r in h1] == list(range(len(h1))) and len(sets) > 1
    assert sets == {r for r, _ in rule_topologies(sysid_small.particles, parse_ranges(())["spring_radius"],
                                                  30, 8)}  # exactly the rule's sets, not a continuous search
    assert all(sum(r["params"]["spring_radius"] == s for r in h1) <= 2 * 8 for s in sets)
    # two rounds of stages 2 and 3 (--rounds 2), their rows numbered on from one round to the next
    assert [(r["round"], r["epoch"]) for r in rep["stage2_history"]] == [(1, 0), (1, 1), (2, 2), (2, 3)]
    evals = [r["evaluation"] for r in rep["stage3_history"]]
    assert evals == list(range(len(evals))) and {r["round"] for r in rep["stage3_history"]} == {1, 2}
    # stage 4 (opt-in) ran its whole budget after stage 3 and, as the last stage, is the one kept
    assert rep["stages"]["stage4"] and len(rep["stage4_history"]) == 6
    assert rep["selection"]["kept"] == "stage4" and "stage4" in rep["evaluations"]
    assert rep["stage4_history"][-1]["best"] <= rep["stage4_history"][0]["loss"]
    assert set(rep["config"]["cma"]) >= {"budget", "search", "ranges"}
    assert (tmp_path / "out" / "rope" / "object.json").is_file()
    assert (tmp_path / "out" / "sysid_report.png").is_file()
    assert main(SysIdConfig(data=tmp_path / "missing", progress=False)) == 2
    assert "not found" in capsys.readouterr().err
