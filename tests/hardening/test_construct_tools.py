"""Construction tools under bad options and files (issue 25): mesh-to-object options out of range and
calibration files with NaN or malformed numbers are one line naming the option or field, exit code 2,
and nothing is written."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from twinbench.cli import main as cli


@pytest.fixture(scope="module")
def ball(tmp_path_factory):
    path = tmp_path_factory.mktemp("mesh") / "ball.stl"
    trimesh.creation.icosphere(subdivisions=2, radius=0.03).export(path)
    return path


@pytest.mark.parametrize(("args", "needle"), [
    (["--rgb", "nan", "nan", "nan"], "rgb: expected 3 values in [0, 1]"),
    (["--rgb", "0.5", "2", "0.5"], "rgb: expected 3 values in [0, 1]"),
    (["--max-neighbors", "0"], "max_neighbors: expected an integer in [1, 1000]"),
    (["--spacing", "1e-5"], "spacing: 1e-05 m would give about"),
    (["--spacing", "nan"], "spacing: must be a finite length > 0"),
    (["--spacing", "0"], "spacing: must be a finite length > 0"),
    (["--radius-factor", "0.5"], "radius_factor: expected a number in [1, 10]"),
    (["--spring-Y", "inf"], "spring_Y: expected a finite stiffness > 0"),
])
def test_mesh_to_object_options_out_of_range(ball, tmp_path, capsys, args, needle):
    out = tmp_path / "obj"
    assert cli(["mesh-to-object", str(ball), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not out.exists()


def _camera(**kw):
    cam = {"name": "front", "intrinsics": [300.0, 300.0, 160.0, 120.0], "sensor_size": [320, 240],
           "camera_to_world": np.eye(4).tolist()}
    cam.update(kw)
    return cam


@pytest.mark.parametrize(("cam", "needle"), [
    (_camera(intrinsics=[float("nan"), 3.0, 1.0, 1.0]), "cameras['front'].intrinsics: expected 4 finite"),
    (_camera(intrinsics="fx fy"), "cameras['front'].intrinsics: expected 4 finite"),
    (_camera(K=[[1, 0], [0, 1]], intrinsics=None), "cameras['front'].K: expected 3x3 finite"),
    (_camera(camera_to_world=[[float("nan")] * 4] * 4), "cameras['front'].camera_to_world: expected 4x4"),
    (_camera(sensor_size=[float("nan"), 240]), "cameras['front'].sensor_size: expected 2 finite"),
    (_camera(sensor_size=[320.5, 240]), "cameras['front'].sensor_size: expected 2 whole pixel counts"),
    (_camera(crop=[0, 0, "w", 10]), "cameras['front'].crop: expected 4 finite"),
])
def test_calibration_fields_are_named(tmp_path, cam, needle):
    from twinbench.construct.calibration import load_calibration

    cam = {k: v for k, v in cam.items() if v is not None}
    path = tmp_path / "calibration.json"
    path.write_text(json.dumps({"cameras": [cam]}))
    with pytest.raises(ValueError) as err:
        load_calibration(path)
    assert str(err.value).startswith(f"{path}: ") and needle in str(err.value), err.value


def _cloud_file(path, means):
    from twinbench.gaussians.cloud import GaussianCloud
    from twinbench.gaussians.io import save_gaussians

    n = len(means)
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    save_gaussians(GaussianCloud(means, quats, np.full((n, 3), -5.0), np.zeros(n), np.zeros((n, 1, 3))), path)
    return path


@pytest.fixture(scope="module")
def robot_ply(tmp_path_factory):
    """A small cloud, for the option checks (they run before any registration)."""
    rng = np.random.default_rng(0)
    return _cloud_file(tmp_path_factory.mktemp("robot") / "robot.ply", rng.uniform(-0.3, 0.3, (500, 3)))


@pytest.mark.parametrize(("args", "needle"), [
    (["--max-distance", "nan"], "--max-distance: expected a length in (0, 10] m"),
    (["--max-distance", "0"], "--max-distance: expected a length in (0, 10] m"),
    (["--voxel", "0"], "--voxel: expected a length in (0, 10] m"),
    (["--voxel", "-0.01"], "--voxel: expected a length in (0, 10] m"),
])
def test_align_robot_options_out_of_range(robot_ply, tmp_path, capsys, args, needle):
    out = tmp_path / "aligned"
    assert cli(["align-robot", str(robot_ply), "--out", str(out), *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and needle in err[0], err
    assert not out.exists()


def test_align_robot_refuses_identical_points(tmp_path, capsys):
    path = _cloud_file(tmp_path / "robot.ply", np.full((200, 3), 0.1))
    out = tmp_path / "aligned"
    assert cli(["align-robot", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "fewer than 10 distinct points" in err[0], err
    assert not out.exists()
