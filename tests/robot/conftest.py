"""Fixtures for the robot tests: the built-in arm with each tool (loaded once)."""

from __future__ import annotations

import pytest

from twinbench.robot.builtin import load_builtin_arm
from twinbench.robot.model import load_robot

# pan, shoulder, elbow, wrist pitch and a tool whose z axis continues the forearm: its turn about the vertical
# when it points down is the pan's, set by where the tool is (an SO-100-like arm, as few joints as that)
FOUR_JOINT_ARM = """<robot name="four"><link name="base"/><link name="l1"/><link name="l2"/><link name="l3"/>
<link name="l4"/><link name="tool"/>
<joint name="pan" type="revolute"><parent link="base"/><child link="l1"/><origin xyz="0 0 0.1"/>
<axis xyz="0 0 1"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
<joint name="shoulder" type="revolute"><parent link="l1"/><child link="l2"/><origin xyz="0 0 0.05"/>
<axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
<joint name="elbow" type="revolute"><parent link="l2"/><child link="l3"/><origin xyz="0.15 0 0"/>
<axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
<joint name="wrist" type="revolute"><parent link="l3"/><child link="l4"/><origin xyz="0.15 0 0"/>
<axis xyz="0 1 0"/><limit lower="-3" upper="3" effort="1" velocity="1"/></joint>
<joint name="tip" type="fixed"><parent link="l4"/><child link="tool"/>
<origin xyz="0.05 0 0" rpy="0 1.5707963267948966 0"/></joint></robot>"""


@pytest.fixture(scope="session")
def arm():
    return load_builtin_arm("gripper")


@pytest.fixture(scope="session")
def pusher_arm():
    return load_builtin_arm("pusher")


@pytest.fixture(scope="session")
def four_joint_arm(tmp_path_factory):
    path = tmp_path_factory.mktemp("four") / "four.urdf"
    path.write_text(FOUR_JOINT_ARM)
    return load_robot(path, home_q=[0.0, -0.5, 1.0, 1.0])
