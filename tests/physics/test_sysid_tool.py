"""System identification with a kinematic tool (`SysIdData.tool_*`): an object pushed by a pusher, not
gripped by control points. The tool's friction is recovered from the motion; the tool arrays are
validated and travel through the sysid directory and the command."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest

from twinbench.construct.sysid_io import load_sysid_data, save_sysid_data
from twinbench.construct.sysid_synthetic import pushed_block_case
from twinbench.physics.sysid import (
    CMAConfig,
    LossWeights,
    SequenceLoss,
    applicable_parameters,
    build_model,
    evaluate,
    rollout,
    stage1_cma,
)
from twinbench.physics.sysid_data import SysIdFormatError
from twinbench.physics.sysid_guess import tool_contact_distance

TRUE_TOOL_FRICTION = 0.5


@pytest.fixture(scope="module")
def pushed():
    return pushed_block_case(tool_friction=TRUE_TOOL_FRICTION, seed=0)


def test_the_tool_pushes_the_object_and_its_friction_changes_the_motion(pushed):
    data, truth = pushed
    xs = truth["positions"]
    moved = xs[-1].mean(axis=0) - xs[0].mean(axis=0)
    assert moved[0] > 0.03  # pushed along x by the tool's face (the tool goes 7 cm)
    slippery = build_model(data, replace(truth["params"], tool_friction=0.05), truth["sim"])
    low = rollout(slippery, data.controls, data.num_frames - 1, tool=data.tool_path())[0]
    # a slippery tool slides along the face: the block follows it less far sideways (y)
    assert low[-1].mean(axis=0)[1] < xs[-1].mean(axis=0)[1] - 0.003
    no_tool = replace(data, tool_vertices=None, tool_faces=None, tool_poses=None)
    without = build_model(no_tool, truth["params"], truth["sim"])
    still = rollout(without, data.controls, data.num_frames - 1)[0]
    assert np.abs(still[-1] - still[0]).max() < 1e-3  # nothing else moves it


def test_stage1_recovers_the_tool_friction(pushed):
    data, truth = pushed
    start = replace(truth["params"], tool_friction=0.2)
    assert "tool_friction" in applicable_parameters(data, truth["sim"])
    best, history = stage1_cma(data, truth["sim"], start, CMAConfig(budget=24, search=("tool_friction",),
                                                                    patience=0), log=lambda _m: None)
    assert len(history) == 24
    assert abs(best.tool_friction - TRUE_TOOL_FRICTION) < 0.1

    def error(params):
        model = build_model(data, params, truth["sim"])
        return evaluate(model, data, SequenceLoss(data, LossWeights())).val_error

    assert error(best) < error(start)


def test_tool_arrays_are_validated_and_saved(pushed, tmp_path):
    data, _ = pushed
    back = load_sysid_data(save_sysid_data(data, tmp_path / "case").parent)
    assert back.has_tool
    np.testing.assert_array_equal(back.tool_poses, data.tool_poses)
    np.testing.assert_array_equal(back.tool_faces, data.tool_faces)
    np.testing.assert_allclose(back.tool_path(), data.tool_path())
    with pytest.raises(SysIdFormatError, match="tool_poses.*is missing"):
        replace(data, tool_poses=None)
    skew = data.tool_poses.copy()
    skew[3, 0, 0] = 2.0
    with pytest.raises(SysIdFormatError, match="tool_poses.*frame 3 is not a rigid"):
        replace(data, tool_poses=skew)
    with pytest.raises(SysIdFormatError, match="tool_faces.*outside"):
        replace(data, tool_faces=data.tool_faces + 100)
    with pytest.raises(SysIdFormatError, match="tool_poses.*shape"):
        replace(data, tool_poses=data.tool_poses[:-1])
    assert not replace(data, tool_vertices=None, tool_faces=None, tool_poses=None).has_tool


def test_cli_fits_and_prints_the_tool_contact(pushed, tmp_path, capsys):
    from twinbench.cli import main as cli_main

    data, truth = pushed
    save_sysid_data(data, tmp_path / "case")
    sim = truth["sim"]
    rc = cli_main(["sysid", "--data", str(tmp_path / "case"), "--out-dir", str(tmp_path / "out"),
                   "--substeps", str(sim.substeps), "--dt", str(sim.dt), "--no-progress", "--no-stage2",
                   "--no-stage3", "--no-guess", "--cma.search", "tool_friction", "--cma.budget", "6",
                   "--initial.spring-Y", "3000", "--initial.dashpot-damping", "50",
                   "--initial.drag-damping", "1"])
    assert rc == 0
    assert "tool contact: friction" in capsys.readouterr().err
    assert (tmp_path / "out" / "block" / "object.json").is_file()
    rep = json.loads((tmp_path / "out" / "sysid_report.json").read_text())
    assert rep["config"]["mesh_margin"] == 0.005 and "tool_friction" in rep["global_params"]
    rc = cli_main(["sysid", "--data", str(tmp_path / "case"), "--out-dir", str(tmp_path / "out2"),
                   "--no-progress", "--mesh-margin", "-0.01"])
    assert rc == 2 and "--mesh-margin" in capsys.readouterr().err
    # the contact distance measured from the push instead (the block's points stop at the case's 5 mm; the
    # nearest noisy point a little nearer), in the report's config
    rc = cli_main(["sysid", "--data", str(tmp_path / "case"), "--out-dir", str(tmp_path / "out3"),
                   "--no-progress", "--no-stage1", "--no-stage2", "--no-stage3", "--measure-mesh-margin"])
    assert rc == 0 and "tool contact distance measured from the push" in capsys.readouterr().err
    rep = json.loads((tmp_path / "out3" / "sysid_report.json").read_text())
    assert rep["config"]["mesh_margin"] == tool_contact_distance(data)[0]
    assert 0.004 < rep["config"]["mesh_margin"] < 0.0052
    # a recording without a tool has no contact distance to measure: a clear refusal
    save_sysid_data(replace(data, tool_vertices=None, tool_faces=None, tool_poses=None), tmp_path / "still")
    rc = cli_main(["sysid", "--data", str(tmp_path / "still"), "--out-dir", str(tmp_path / "out4"),
                   "--no-progress", "--measure-mesh-margin"])
    assert rc == 2 and "no tool in this recording" in capsys.readouterr().err


@pytest.mark.parametrize("margin", [0.003, 0.010])
def test_the_tool_contact_distance_is_measured_from_the_push(margin):
    # the tool starts 4 mm outside its contact distance, so the block's points stop at that distance from it;
    # the recording's noisy points (1 mm) give it back within a millimetre, a little low (the nearest of
    # several noisy points), from the frames where the tool carries the block
    data, truth = pushed_block_case(seed=1, mesh_margin=margin, gap=margin + 0.004)
    distance, frames = tool_contact_distance(data)
    assert margin - 1e-3 < distance < margin + 2e-4
    # the frames used are the push's: the tool moves (after 0.1 s) and the block's points move with it
    moved = np.linalg.norm(np.diff(truth["positions"].mean(axis=1), axis=0), axis=1)
    assert len(frames) >= 10 and frames.min() >= 3 and (moved[frames - 1] > 1e-3).all()


def test_a_recording_without_a_push_gives_no_contact_distance(pushed):
    data, _ = pushed
    with pytest.raises(ValueError, match="no tool in this recording"):
        tool_contact_distance(replace(data, tool_vertices=None, tool_faces=None, tool_poses=None))
    # the tool moves well away from the block: it never carries it
    away = data.tool_poses.copy()
    away[:, 0, 3] -= 0.2 + 0.2 * np.arange(data.num_frames) / data.num_frames
    with pytest.raises(ValueError, match=r"carries the object in 0 frame\(s\).*--mesh-margin"):
        tool_contact_distance(replace(data, tool_poses=away))
