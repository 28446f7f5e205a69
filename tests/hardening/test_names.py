"""Names that become file names (twin, object, collider, camera, box, --name) follow the one name rule of
run ids (`twinbench.errors.check_name`): a name that is a path is refused (one line, exit 2, the file and
field named) and nothing is written outside the output folder. `twin build` copies only the URDF and the
meshes it references (issue 25)."""

from __future__ import annotations

import dataclasses
import json
import shutil

import numpy as np
import pytest

from twinbench.cli import main as cli
from twinbench.errors import InputError, check_name
from twinbench.twin import load_twin, save_object, save_twin
from twinbench.twin.cells import push_t_cell

ESCAPES = ["../../../../escaped", "/tmp/twinbench_escaped_abs", "a/b", ".hidden", "-x", "", "x" * 129, 5]


@pytest.mark.parametrize("bad", ESCAPES)
def test_the_name_rule_refuses_paths(bad):
    with pytest.raises(InputError, match="objects: name"):
        check_name(bad, "objects: name")


def test_the_name_rule_keeps_plain_names():
    for ok in ("push-t-fast", "tblock", "front", "cam_0", "v1.2", "x" * 128):
        assert check_name(ok, "name") == ok


def _one_line(capsys, argv, *needles):
    assert cli(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    for needle in needles:
        assert needle in err[0], err[0]


@pytest.fixture(scope="module")
def twin_dir(tmp_path_factory):
    return save_twin(push_t_cell("fast"), tmp_path_factory.mktemp("twin") / "t").parent


def _edited(twin_dir, tmp_path, edit):
    out = tmp_path / "twin"
    shutil.copytree(twin_dir, out)
    doc = json.loads((out / "twin.json").read_text())
    edit(doc)
    (out / "twin.json").write_text(json.dumps(doc))
    return out


def _nothing_escaped(tmp_path):
    found = [p for p in tmp_path.parent.rglob("escaped*")] + list(tmp_path.parent.parent.glob("escaped*"))
    assert not found, found


def test_twin_show_refuses_a_camera_name_that_is_a_path(twin_dir, tmp_path, capsys):
    def edit(doc):
        doc["cameras"][0]["name"] = "../../../../escaped_cam"
    folder = _edited(twin_dir, tmp_path, edit)
    _one_line(capsys, ["twin", "show", str(folder), "--out-dir", str(tmp_path / "out" / "a")],
              "twin.json", "cameras: name '../../../../escaped_cam'")
    _nothing_escaped(tmp_path)


@pytest.mark.parametrize("name", ["../../../escaped_twin", "/tmp/escaped_twin_abs"])
def test_twin_show_refuses_a_twin_name_that_is_a_path(twin_dir, tmp_path, capsys, name, monkeypatch):
    monkeypatch.chdir(tmp_path)  # the default output folder is outputs/twin_show/<twin name>

    def edit(doc):
        doc["name"] = name
    folder = _edited(twin_dir, tmp_path, edit)
    _one_line(capsys, ["twin", "show", str(folder)], "twin.json", f"name {name!r}")
    _nothing_escaped(tmp_path)
    assert not (tmp_path / "outputs").exists()


def test_load_twin_refuses_object_and_collider_names_that_are_paths(twin_dir, tmp_path):
    def edit(doc):
        doc["objects"][0]["name"] = "../escaped_obj"
    with pytest.raises(InputError, match=r"twin\.json.*objects: name '\.\./escaped_obj'"):
        load_twin(_edited(twin_dir, tmp_path, edit))


def test_a_collider_spec_refuses_a_path_name():
    from twinbench.twin import ColliderSpec

    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0.0]])
    with pytest.raises(ValueError, match="colliders: name '../escaped'"):
        ColliderSpec("../escaped", v, np.array([[0, 1, 2]]))


# ---- twin build ---------------------------------------------------------------------------------------
def _build_config(tmp_path, *, object_name=None, collider_name=None, stored_name=None):
    spec = push_t_cell("fast")
    block = spec.objects[0]
    if stored_name is not None:
        obj_dir = tmp_path / "objects" / "tblock"
        save_object(block, obj_dir)
        doc = json.loads((obj_dir / "object.json").read_text())
        doc["object"]["name"] = stored_name
        (obj_dir / "object.json").write_text(json.dumps(doc))
    else:
        save_object(block, tmp_path / "objects" / "tblock")
    cam = spec.cameras[0]
    calib = {"cameras": [{"name": cam.name, "intrinsics": list(cam.intrinsics),
                          "sensor_size": list(cam.sensor_size), "camera_to_world": cam.pose.tolist()}]}
    (tmp_path / "calibration.json").write_text(json.dumps(calib))
    entry = {"dir": "objects/tblock"}
    if object_name is not None:
        entry["name"] = object_name
    config = {"name": "cell", "robot": {"urdf": "builtin:xarm7_pusher"}, "objects": [entry],
              "cameras": "calibration.json"}
    if collider_name is not None:
        import trimesh

        trimesh.creation.box(extents=(0.1, 0.1, 0.1)).export(tmp_path / "box.obj")
        config["colliders"] = [{"name": collider_name, "mesh": "box.obj"}]
    (tmp_path / "build.json").write_text(json.dumps(config))
    return tmp_path / "build.json"


@pytest.mark.parametrize("field", ["objects[0].name", "colliders[0].name"])
def test_twin_build_refuses_config_names_that_are_paths(tmp_path, capsys, field):
    bad = "../../escaped_part"
    kw = {"object_name": bad} if field.startswith("objects") else {"collider_name": bad}
    config = _build_config(tmp_path / "in", **kw)
    _one_line(capsys, ["twin", "build", str(config), "--out", str(tmp_path / "in" / "out" / "twin")],
              "build.json", field)
    _nothing_escaped(tmp_path / "in" / "out")


def test_twin_build_refuses_an_object_json_name_that_is_a_path(tmp_path, capsys):
    config = _build_config(tmp_path / "in", stored_name="../../escaped_part")
    _one_line(capsys, ["twin", "build", str(config), "--out", str(tmp_path / "in" / "out" / "twin")],
              "object.json", "objects: name")
    _nothing_escaped(tmp_path / "in" / "out")


def test_twin_build_copies_only_the_urdf_and_its_meshes(tmp_path):
    from twinbench.robot.builtin import ASSETS
    from twinbench.robot.model import load_robot

    src = ASSETS / "xarm7_pusher.urdf"
    robot_dir = tmp_path / "myrobot"
    shutil.copytree(src.parent, robot_dir)
    (robot_dir / "id_rsa").write_text("-----BEGIN OPENSSH PRIVATE KEY-----\n")
    (robot_dir / "big.bin").write_bytes(b"\0" * 1_000_000)
    spec = push_t_cell("fast")
    spec = dataclasses.replace(spec, robot=dataclasses.replace(
        spec.robot, urdf=str(robot_dir / src.name), tool_radius=None))
    path = save_twin(spec, tmp_path / "twin")
    copied = sorted(p.relative_to(path.parent / "robot").as_posix()
                    for p in (path.parent / "robot").rglob("*") if p.is_file())
    referenced = {m.split("/")[-1] for m in (robot_dir / src.name).read_text().split('filename="')[1:]
                  for m in [m.split('"')[0]]}
    assert src.name in copied and "id_rsa" not in copied and "big.bin" not in copied
    assert not any(name.endswith(".urdf") and name != src.name for name in copied)
    assert {p.split("/")[-1] for p in copied if p != src.name} == referenced
    robot = load_robot(path.parent / "robot" / src.name)  # the copy loads with its meshes
    assert robot.n_q == 7


# ---- segment, align-color, --name ---------------------------------------------------------------------
def test_segment_refuses_a_box_name_that_is_a_path(tmp_path, capsys):
    from twinbench.gaussians.io import save_gaussians
    from twinbench.gaussians.primitives import surface_discs

    pts = np.random.default_rng(0).uniform(0, 0.1, (50, 3))
    save_gaussians(surface_discs(pts, np.tile([0, 0, 1.0], (50, 1)), np.full((50, 3), 0.5), 0.003),
                   tmp_path / "scan.ply")
    box = {"center": [0.05, 0.05, 0.05], "half_extents": [0.1, 0.1, 0.1]}
    (tmp_path / "boxes.json").write_text(json.dumps({"robot": box, "objects": {"../../../escaped_box": box}}))
    _one_line(capsys, ["segment", str(tmp_path / "scan.ply"), "--boxes", str(tmp_path / "boxes.json"),
                       "--out", str(tmp_path / "out" / "seg")], "boxes.json", "objects: name")
    _nothing_escaped(tmp_path / "out")


def test_align_color_refuses_a_calibration_camera_name_that_is_a_path(tmp_path, capsys):
    from twinbench.gaussians.io import save_gaussians
    from twinbench.gaussians.primitives import surface_discs

    pts = np.random.default_rng(0).uniform(0, 0.1, (50, 3))
    save_gaussians(surface_discs(pts, np.tile([0, 0, 1.0], (50, 1)), np.full((50, 3), 0.5), 0.003),
                   tmp_path / "scan.ply")
    cam = {"name": "../../../../escaped_calib", "intrinsics": [100, 100, 50, 50], "sensor_size": [100, 100],
           "camera_to_world": np.eye(4).tolist()}
    (tmp_path / "calibration.json").write_text(json.dumps({"cameras": [cam]}))
    (tmp_path / "real").mkdir()
    _one_line(capsys, ["align-color", "--scan", str(tmp_path / "scan.ply"), "--calibration",
                       str(tmp_path / "calibration.json"), "--real", str(tmp_path / "real"),
                       "--out", str(tmp_path / "out" / "color")],
              "calibration.json", "cameras[0].name")
    _nothing_escaped(tmp_path / "out")


def test_mesh_to_object_refuses_a_name_that_is_a_path(tmp_path, capsys):
    import trimesh

    trimesh.creation.icosphere(subdivisions=1, radius=0.03).export(tmp_path / "ball.stl")
    _one_line(capsys, ["mesh-to-object", str(tmp_path / "ball.stl"), "--name", "../../escaped_mesh",
                       "--out", str(tmp_path / "out" / "o")], "--name '../../escaped_mesh'")
    _nothing_escaped(tmp_path / "out")


def test_import_phystwin_refuses_a_name_that_is_a_path(tmp_path, capsys):
    _one_line(capsys, ["import-phystwin", str(tmp_path), "--name", "../../escaped_pt",
                       "--out", str(tmp_path / "out" / "o")], "--name '../../escaped_pt'")
    _nothing_escaped(tmp_path / "out")
