"""The real xArm 7 from example-robot-data (extra `xarm`): loads, FK agrees with the URDF joint origins."""

from __future__ import annotations

import importlib.metadata
from xml.etree import ElementTree

import numpy as np
import pytest

from twinbench.robot.builtin import load_xarm7, xarm7_urdf_path

try:
    importlib.metadata.distribution("example-robot-data")
except importlib.metadata.PackageNotFoundError:
    pytest.skip(
        "example-robot-data is not installed (pip install 'twinbench[xarm]')", allow_module_level=True
    )


def _rpy_matrix(r, p, y):
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _chain_from_xml(path, q):
    """Flange pose by chaining the XML joint origins of joint1..joint7 (all axes z) with rotations q."""
    joints = {j.get("name"): j for j in ElementTree.parse(path).getroot().findall("joint")}
    t = np.eye(4)
    for k in range(7):
        j = joints[f"joint{k + 1}"]
        o = j.find("origin")
        step = np.eye(4)
        step[:3, :3] = _rpy_matrix(*map(float, o.get("rpy").split()))
        step[:3, 3] = list(map(float, o.get("xyz").split()))
        assert j.find("axis").get("xyz").split() == ["0", "0", "1"]
        rot = np.eye(4)
        rot[:3, :3] = _rpy_matrix(0.0, 0.0, q[k])
        t = t @ step @ rot
    return t


def test_real_xarm7_loads_and_fk_matches_urdf_joint_origins():
    model = load_xarm7()
    assert model.joint_names == [f"joint{k}" for k in range(1, 8)]
    assert {f"link{k}" for k in range(1, 8)} <= set(model.visual_meshes)
    path = xarm7_urdf_path()
    rng = np.random.default_rng(0)
    for q in [np.zeros(7), *rng.uniform(-2.0, 2.0, size=(5, 7))]:
        np.testing.assert_allclose(model.link_pose(q, "link7"), _chain_from_xml(path, q), atol=1e-12)


def test_builtin_arm_kinematics_match_the_real_xarm7(arm):
    # The built-in arm writes the real URDF's +-1.5708 as exact +-pi/2: flange poses agree to ~1e-5.
    real = load_xarm7(load_meshes=False)
    rng = np.random.default_rng(1)
    qs = rng.uniform(np.maximum(real.lower, -3), np.minimum(real.upper, 3), size=(50, 7))
    flange_real = real.fk(qs)[:, real.link_index("link7")]
    q_built = np.concatenate([qs, np.zeros((50, 1))], axis=1)
    flange_built = arm.fk(q_built)[:, arm.link_index("link7")]
    np.testing.assert_allclose(flange_built, flange_real, atol=5e-5)
    np.testing.assert_allclose(real.lower, arm.lower[:7])
    np.testing.assert_allclose(real.upper, arm.upper[:7])
