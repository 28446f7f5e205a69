"""`twinbench robot-info`: built-in arm and a given URDF."""

from __future__ import annotations

import re

import numpy as np

from twinbench.cli import main
from twinbench.robot.builtin import load_builtin_arm
from twinbench.transforms import matrix_to_quat


def _ee_line(out: str):
    m = re.search(r"at home: position \[([^\]]+)\] m, quaternion wxyz \[([^\]]+)\]", out)
    assert m, out
    return np.array(m.group(1).split(", "), dtype=float), np.array(m.group(2).split(", "), dtype=float)


def test_robot_info_builtin(capsys, arm):
    assert main(["robot-info"]) == 0
    out = capsys.readouterr().out
    for name in arm.link_names:
        assert f"  {name}" in out
    assert re.search(
        r"joint4\s+revolute\s+link3 -> link4\s+axis \[\+0.000 \+0.000 \+1.000\]\s+"
        r"limits \[-0.1920, \+3.9270\]",
        out,
    )
    assert "mimic left_finger_joint" in out
    pos, quat = _ee_line(out)
    ee = arm.ee_pose(arm.home_q)
    np.testing.assert_allclose(pos, ee[:3, 3], atol=1e-4)
    np.testing.assert_allclose(quat, matrix_to_quat(ee[:3, :3]), atol=1e-4)


def test_robot_info_pusher_and_urdf(capsys, tmp_path):
    assert main(["robot-info", "--tool", "pusher"]) == 0
    out = capsys.readouterr().out
    assert "contact links: pusher" in out and "fewer than 6" not in out  # the xArm: 7 joints
    faces = len(load_builtin_arm("pusher").collision_meshes["pusher"].faces)  # what physics refits
    assert re.search(rf"\n  pusher  mesh: \d+ vertices  collision: {faces:,} faces\n", out)
    urdf = tmp_path / "two.urdf"
    urdf.write_text("""<robot name="two"><link name="a"/><link name="b"/>
      <joint name="hinge" type="revolute"><parent link="a"/><child link="b"/>
      <origin xyz="0 0 0.5" rpy="0 0 0"/><axis xyz="0 1 0"/>
      <limit lower="-1" upper="1" effort="1" velocity="1"/></joint></robot>""")
    assert main(["robot-info", str(urdf)]) == 0
    out = capsys.readouterr().out
    assert "hinge" in out and "limits [-1.0000, +1.0000]" in out
    assert "arm joints (root to end effector): hinge (fewer than 6: a tool pointing down turns" in out
    pos, quat = _ee_line(out)
    np.testing.assert_allclose(pos, [0, 0, 0.5])
    np.testing.assert_allclose(quat, [1, 0, 0, 0])


def test_robot_info_names_the_gripper_joint_and_the_end_effector_it_implies(capsys, tmp_path):
    # Unitree Z1's ending: a fixed stator and one revolute jaw; named as the gripper, the jaw is a finger
    # and the stator the end effector
    urdf = tmp_path / "z1like.urdf"
    urdf.write_text("""<robot name="z1like"><link name="base"/><link name="stator"/><link name="jaw"/>
      <joint name="fix" type="fixed"><parent link="base"/><child link="stator"/>
      <origin xyz="0 0 0.3"/></joint>
      <joint name="jaw_joint" type="revolute"><parent link="stator"/><child link="jaw"/>
      <origin xyz="0.1 0 0"/><axis xyz="0 1 0"/><limit lower="-1.5" upper="0" effort="1" velocity="1"/>
      </joint></robot>""")
    assert main(["robot-info", str(urdf)]) == 0
    assert "end effector jaw at home" in capsys.readouterr().out
    assert main(["robot-info", str(urdf), "--gripper-joint", "jaw_joint"]) == 0
    out = capsys.readouterr().out
    assert "end effector stator at home" in out and "gripper joint jaw_joint: open 0, closed -1.5" in out
