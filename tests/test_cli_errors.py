"""Every `twinbench` command: bad input is ONE line on stderr naming the file/argument, exit code 2, and a
traceback only with --debug (issue 14)."""

from __future__ import annotations

import json
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from twinbench.cli import main

URDF_BAD = '<robot name="r"><link name="a"/><joint name="j" type="revolute"><parent link="a"/>'


def _case(tmp_path, name):
    """(argv, text the one error line must contain) of a bad-input case."""
    db = tmp_path / "r.sqlite"
    if name == "malformed-urdf":
        (tmp_path / "bad.urdf").write_text(URDF_BAD)
        return ["robot-info", str(tmp_path / "bad.urdf")], "bad.urdf: malformed XML"
    if name == "missing-urdf":
        return ["robot-info", str(tmp_path / "nope.urdf")], "nope.urdf"
    if name == "bad-tool":
        return ["robot-info", "--tool", "hammer"], "--tool"
    if name == "bad-lerobot-info":
        (tmp_path / "ds" / "meta").mkdir(parents=True)
        (tmp_path / "ds" / "meta" / "info.json").write_text("{codebase_version: v3")
        return ["replay", "--source", str(tmp_path / "ds"), "--db", str(db)], "info.json: not valid JSON"
    if name == "missing-replay-source":
        return (["replay", "--source", str(tmp_path / "nope.json"), "--db", str(db)],
                "nope.json does not exist")
    if name == "replay-env-kwargs":
        return ["replay", "--source", "x.json", "--env-kwargs", "{oops"], "--env-kwargs must be a JSON object"
    if name == "eval-db-under-a-file":
        (tmp_path / "afile").write_text("x")
        return (["eval", "--run-id", "r", "--task", "point-reach", "--policy", "expert", "--db",
                 str(tmp_path / "afile" / "r.sqlite")], "cannot create its folder")
    if name == "eval-db-not-sqlite":
        (tmp_path / "notes.sqlite").write_text("these are my notes, not a database" * 100)
        return (["eval", "--run-id", "r", "--task", "point-reach", "--policy", "expert", "--db",
                 str(tmp_path / "notes.sqlite")], "notes.sqlite is not a twinbench results store")
    if name == "eval-other-protocol":
        from twinbench.evaluation.store import ResultsStore

        ResultsStore(db).start_run("r", "point-reach", {"task": "point-reach", "policies": ["other"]})
        return (["eval", "--run-id", "r", "--task", "point-reach", "--policy", "expert", "--episodes", "1",
                 "--db", str(db), "--output-dir", str(tmp_path)], "already exists in")
    if name == "eval-unknown-task":
        return ["eval", "--run-id", "r", "--task", "nope", "--policy", "expert", "--db", str(db)], "'nope'"
    if name == "eval-run-id-path":
        return (["eval", "--run-id", "../../x", "--task", "point-reach", "--policy", "expert",
                 "--db", str(db)], "run id '../../x'")
    if name == "eval-bad-policy":
        return ["eval", "--run-id", "r", "--task", "point-reach", "--policy", "nonsense", "--db", str(db)], \
            "nonsense"
    if name == "eval-twin-on-point-reach":
        return (["eval", "--run-id", "r", "--task", "point-reach", "--policy", "expert", "--twin",
                 str(tmp_path / "twin"), "--db", str(db)], "--twin: task 'point-reach' has an env of its own")
    if name == "eval-device-not-here":  # Warp's own error was an internal error from inside the episode
        return (["eval", "--run-id", "r", "--task", "push-t", "--policy", "expert", "--episodes", "1",
                 "--env-kwargs", '{"preset": "fast", "device": "cuda:99"}', "--db", str(db),
                 "--output-dir", str(tmp_path)], "--env-kwargs device 'cuda:99'")
    if name == "render-device-not-here":
        return (["render-ply", str(tmp_path / "none.ply"), "--out", str(tmp_path / "x.png"), "--device",
                 "cuda:99"], "--device 'cuda:99'")
    if name == "import-real-missing":
        return ["import-real", str(tmp_path / "none.csv"), "--db", str(db)], "none.csv does not exist"
    if name == "report-unknown-run":
        return ["report", "--run-id", "nope", "--db", str(db), "--out", str(tmp_path / "r.html")], "'nope'"
    if name == "render-missing":
        return ["render-ply", str(tmp_path / "none.ply"), "--out", str(tmp_path / "x.png")], "none.ply"
    if name.startswith("refine-"):
        from twinbench.gaussians.io import save_gaussians
        from twinbench.gaussians.primitives import surface_discs

        pts = np.random.default_rng(0).uniform(0, 0.1, (50, 3))
        save_gaussians(surface_discs(pts, np.tile([0, 0, 1.0], (50, 1)), np.full((50, 3), 0.5), 0.003),
                       tmp_path / "scan.ply")
        cam = {"name": "front", "intrinsics": [400, 400, 120, 120], "sensor_size": [240, 240],
               "camera_to_world": np.eye(4).tolist()}
        (tmp_path / "calibration.json").write_text(json.dumps({"cameras": [cam]}))
        (tmp_path / "real").mkdir()
        argv = ["refine-cameras", "--scan", str(tmp_path / "scan.ply"), "--calibration",
                str(tmp_path / ("none.json" if name == "refine-missing-calibration" else "calibration.json")),
                "--real", str(tmp_path / "real"), "--out", str(tmp_path / "cams")]
        if name == "refine-missing-calibration":
            return argv, "none.json"
        if name == "refine-no-real-image":
            return argv, "no real image NAME.png for any static camera"
        iio.imwrite(tmp_path / "real" / "front.png", np.zeros((240, 240, 3), np.uint8))
        return argv, "front.png: camera 'front': the scan covers"  # the camera sees little of the scan
    raise AssertionError(name)


CASES = ["malformed-urdf", "missing-urdf", "bad-tool", "bad-lerobot-info", "missing-replay-source",
         "replay-env-kwargs", "eval-db-under-a-file", "eval-db-not-sqlite", "eval-other-protocol",
         "eval-unknown-task", "eval-run-id-path", "eval-bad-policy", "eval-twin-on-point-reach",
         "eval-device-not-here", "render-device-not-here", "import-real-missing",
         "report-unknown-run", "render-missing", "refine-missing-calibration", "refine-no-real-image",
         "refine-scan-out-of-view"]


@pytest.mark.parametrize("name", CASES)
def test_bad_input_is_one_line_and_exit_code_2(tmp_path, capsys, name):
    argv, needle = _case(tmp_path, name)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"twinbench {argv[0]}: ") and needle in err[0], err[0]
    assert "Traceback" not in err[0]


def test_debug_shows_the_traceback(tmp_path):
    (tmp_path / "bad.urdf").write_text(URDF_BAD)
    cmd = [sys.executable, "-m", "twinbench.cli", "robot-info", str(tmp_path / "bad.urdf")]
    plain = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert plain.returncode == 2 and "Traceback" not in plain.stderr
    assert len(plain.stderr.strip().splitlines()) == 1
    debug = subprocess.run(cmd + ["--debug"], capture_output=True, text=True, timeout=60)
    assert debug.returncode != 0 and "Traceback" in debug.stderr and "URDFError" in debug.stderr


def test_an_internal_error_is_one_line_exit_1(monkeypatch, capsys):
    import twinbench.commands.robot_info as info

    def boom(config):
        raise ZeroDivisionError("division by zero in a helper")

    monkeypatch.setattr(info, "main", boom)
    assert main(["robot-info"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "internal error: ZeroDivisionError" in err[0] and "--debug" in err[0]


def test_a_full_disk_is_one_line_exit_1_with_the_free_space_and_the_fix(monkeypatch, capsys, tmp_path):
    import errno
    import os

    import twinbench.commands.robot_info as info

    def full(config):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp_path / "out" / "eval_info.json"))

    monkeypatch.setattr(info, "main", full)
    assert main(["robot-info"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "error: OSError: [Errno 28] No space left on device" in err[0]
    assert f"free on {tmp_path})" in err[0] and err[0].endswith("run the same command again")


def test_import_real_lists_every_bad_row_under_one_summary(tmp_path, capsys):
    csv = tmp_path / "r.csv"
    csv.write_text("policy,checkpoint,init_state,success\na,,x,yes\na,,1,perhaps\n")
    assert main(["import-real", str(csv), "--db", str(tmp_path / "r.sqlite"), "--task", "push-t"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[0] == f"twinbench import-real: error: 2 problem(s) in {csv}; nothing was imported:"
    assert json.dumps(err[1:]).count("r.csv row") == 2
