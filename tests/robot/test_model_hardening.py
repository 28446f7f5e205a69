"""URDF hardening (issue 14): non-tree joint graphs, NaN / inverted values, meshes outside the URDF's tree."""

from __future__ import annotations

import resource
import time

import numpy as np
import pytest
import trimesh

from twinbench.cli import main as cli_main
from twinbench.errors import InputError
from twinbench.robot.model import URDFError, load_robot

LINK = '<link name="{}"/>'
JOINT = ('<joint name="{name}" type="revolute"><parent link="{p}"/><child link="{c}"/>'
         '<origin xyz="{xyz}" rpy="0 0 0"/><axis xyz="0 0 1"/>'
         '<limit lower="{lo}" upper="{hi}" effort="1" velocity="1"/></joint>')


def _urdf(tmp_path, links, joints, name="r.urdf", extra=""):
    body = "".join(LINK.format(n) for n in links) + extra
    for j in joints:
        body += JOINT.format(**{"xyz": "0 0 0.1", "lo": -1, "hi": 1, **j})
    path = tmp_path / name
    path.write_text(f'<robot name="r">{body}</robot>')
    return path


@pytest.mark.parametrize("joints, needle", [
    # base -> a, a -> b, b -> a: the cycle (robot-info used to grow without bound)
    ([dict(name="j0", p="base", c="a"), dict(name="j1", p="a", c="b"), dict(name="j2", p="b", c="a")],
     "child of two joints"),
    # a diamond: b has two parents
    ([dict(name="j0", p="base", c="a"), dict(name="j1", p="base", c="b"), dict(name="j2", p="a", c="b")],
     "child of two joints"),
    # a pure cycle with no root at all
    ([dict(name="j0", p="base", c="a"), dict(name="j1", p="a", c="b"), dict(name="j2", p="b", c="base")],
     "exactly one root"),
    ([dict(name="j0", p="base", c="a"), dict(name="j1", p="a", c="a")], "to itself"),
    ([dict(name="j0", p="base", c="a"), dict(name="j1", p="a", c="ghost")], "unknown link 'ghost'"),
])
def test_joint_graphs_that_are_not_trees_are_refused_at_once(tmp_path, joints, needle):
    path = _urdf(tmp_path, ["base", "a", "b"], joints)
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    t0 = time.monotonic()
    with pytest.raises(URDFError, match=needle):
        load_robot(path, load_meshes=False)
    assert time.monotonic() - t0 < 2
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - rss0 < 50_000  # KiB


def test_robot_info_on_a_cyclic_urdf_is_one_line_exit_2(tmp_path, capsys):
    cycle = [dict(name="j0", p="base", c="a"), dict(name="j1", p="a", c="b"), dict(name="j2", p="b", c="a")]
    path = _urdf(tmp_path, ["base", "a", "b"], cycle)
    assert cli_main(["robot-info", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(path) in err[0] and "tree" in err[0] and "Traceback" not in err[0]


@pytest.mark.filterwarnings("ignore::RuntimeWarning")  # yourdfpy builds the inf origin matrix first
@pytest.mark.parametrize("joint, needle", [
    (dict(xyz="nan 0 0"), "<origin xyz rpy> holds NaN"),
    (dict(xyz="0 inf 0"), "<origin xyz rpy> holds NaN or inf"),
    (dict(lo="nan"), "<limit lower upper> holds NaN"),
    (dict(lo=1, hi=-1), "lower 1 > upper -1; swap them"),
])
def test_nan_origins_and_inverted_limits_are_refused(tmp_path, joint, needle):
    path = _urdf(tmp_path, ["base", "a"], [dict(name="j0", p="base", c="a", **joint)])
    with pytest.raises(URDFError, match=needle) as err:
        load_robot(path, load_meshes=False)
    assert "'j0'" in str(err.value) and str(path) in str(err.value)


def test_a_valid_chain_still_loads_with_the_expected_pose(tmp_path):
    chain = [dict(name="j0", p="base", c="a"), dict(name="j1", p="a", c="b")]
    path = _urdf(tmp_path, ["base", "a", "b"], chain)
    m = load_robot(path, load_meshes=False)
    assert m.link_names == ["base", "a", "b"]
    np.testing.assert_allclose(m.ee_pose(np.zeros(2))[:3, 3], [0, 0, 0.2])


def test_entity_declarations_are_refused(tmp_path):
    path = tmp_path / "laughs.urdf"
    path.write_text('<?xml version="1.0"?><!DOCTYPE r [<!ENTITY a "aaaaaaaaaa">'
                    '<!ENTITY b "&a;&a;&a;&a;&a;&a;&a;&a;&a;&a;">]>'
                    '<robot name="&b;"><link name="base"/></robot>')
    with pytest.raises(URDFError, match="DOCTYPE"):
        load_robot(path, load_meshes=False)


def test_a_xacro_file_is_named_with_the_command_that_expands_it(tmp_path):
    path = tmp_path / "arm.urdf.xacro"
    path.write_text('<?xml version="1.0"?><robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="arm">'
                    '<xacro:property name="L" value="0.3"/><link name="base"/><link name="l1"/>'
                    '<joint name="j" type="fixed"><parent link="base"/><child link="l1"/>'
                    '<origin xyz="0 0 ${L}"/></joint></robot>')
    with pytest.raises(URDFError, match=r"arm\.urdf\.xacro: a xacro file .* `xacro FILE > robot\.urdf`"):
        load_robot(path, load_meshes=False)


def test_a_urdf_that_xacro_generated_loads(tmp_path):
    # xacro's output keeps the namespace declaration and a comment naming xacro (franka_description's
    # panda.urdf, ur_description's): plain values, a URDF like any other.
    path = tmp_path / "panda.urdf"
    path.write_text('<?xml version="1.0"?><!-- autogenerated by xacro from panda.urdf.xacro -->'
                    '<robot xmlns:xacro="http://www.ros.org/wiki/xacro" name="arm"><link name="base"/>'
                    '<link name="l1"/><joint name="j" type="revolute"><parent link="base"/><child link="l1"/>'
                    '<origin xyz="0 0 0.3"/><axis xyz="0 0 1"/><limit lower="-1" upper="1" effort="1" '
                    'velocity="1"/></joint></robot>')
    assert load_robot(path, load_meshes=False).joint_names == ["j"]


def test_a_xacro_substitution_without_macros_is_refused(tmp_path):
    path = tmp_path / "arm.urdf"
    path.write_text('<?xml version="1.0"?><robot name="arm"><link name="base"><visual><geometry>'
                    '<mesh filename="$(find arm_description)/base.stl"/></geometry></visual></link></robot>')
    with pytest.raises(URDFError, match=r"arm\.urdf: a xacro file"):
        load_robot(path, load_meshes=False)


def _mesh_urdf(folder, filename):
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "r.urdf"
    path.write_text(f'<robot name="r"><link name="base"><visual><geometry><mesh filename="{filename}"/>'
                    "</geometry></visual></link></robot>")
    return path


@pytest.mark.parametrize("filename", ["../outside/box.stl", "{abs}", "file://{abs}",
                                      "meshes/../../outside/box.stl", "package://robot/../outside/box.stl",
                                      "../../../../etc/passwd", "/etc/shadow"])
def test_mesh_paths_leaving_the_urdf_tree_are_refused_without_opening(tmp_path, monkeypatch, filename):
    outside = tmp_path / "outside" / "box.stl"
    outside.parent.mkdir()
    trimesh.creation.box(extents=(1, 1, 1)).export(outside)
    opened = []
    monkeypatch.setattr(trimesh, "load", lambda *a, **k: opened.append(a) or trimesh.creation.box())
    path = _mesh_urdf(tmp_path / "robot", filename.format(abs=outside))
    with pytest.raises(URDFError, match="(outside the URDF's folder|leaves its package)") as err:
        load_robot(path)
    assert "'base'" in str(err.value) and opened == []


def test_meshes_inside_the_tree_and_in_package_dirs_still_load(tmp_path):
    robot = tmp_path / "robot"
    (robot / "meshes").mkdir(parents=True)
    trimesh.creation.box(extents=(0.1, 0.2, 0.3)).export(robot / "meshes" / "box.stl")
    m = load_robot(_mesh_urdf(robot, "meshes/box.stl"))
    np.testing.assert_allclose(m.visual_meshes["base"].extents, [0.1, 0.2, 0.3])
    m = load_robot(_mesh_urdf(robot, f"file://{robot / 'meshes' / 'box.stl'}"))
    np.testing.assert_allclose(m.visual_meshes["base"].extents, [0.1, 0.2, 0.3])
    shared = tmp_path / "shared_meshes"
    shared.mkdir()
    trimesh.creation.box(extents=(0.3, 0.2, 0.1)).export(shared / "b.stl")
    urdf = _mesh_urdf(tmp_path / "robot2", str(shared / "b.stl"))
    with pytest.raises(URDFError, match="package_dirs"):
        load_robot(urdf)
    m = load_robot(urdf, package_dirs=[shared])  # an explicitly trusted folder
    np.testing.assert_allclose(m.visual_meshes["base"].extents, [0.3, 0.2, 0.1])


def test_bad_geometry_sizes_and_urdf_error_type(tmp_path):
    path = tmp_path / "g.urdf"
    path.write_text('<robot name="r"><link name="base"><visual><geometry><box size="nan 1 1"/></geometry>'
                    "</visual></link></robot>")
    with pytest.raises(URDFError, match="box size must be 3 finite value"):
        load_robot(path)
    assert issubclass(URDFError, InputError) and issubclass(URDFError, ValueError)
