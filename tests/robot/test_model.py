"""URDF loading, forward kinematics (hand-computed poses), Jacobian, mimic fingers and loader errors."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from twinbench.robot.model import URDFError, load_robot
from twinbench.transforms import axis_angle_to_matrix, invert_pose

DOWN = np.diag([1.0, -1.0, -1.0])  # flange orientation at q = 0: x forward, z pointing down


def _rot_y(a):
    return axis_angle_to_matrix(np.array([0.0, 1.0, 0.0]), np.array(a))


def test_fk_at_zero_matches_hand_computed_chain(arm):
    # Chain by hand: joint1 at z=0.267; joint3 0.293 higher (z=0.560, link3 aligned with the world);
    # joint4 0.0525 forward; joint5 0.0775 forward, 0.3425 down (x=0.130, z=0.2175); joint7 0.076
    # forward and 0.097 down -> flange (0.206, 0, 0.1205) with z pointing down.
    q = np.zeros(arm.n_q)
    t = arm.fk(q)
    pos = {name: t[arm.link_index(name), :3, 3] for name in arm.link_names}
    np.testing.assert_allclose(pos["link1"], [0, 0, 0.267], atol=1e-12)
    np.testing.assert_allclose(pos["link3"], [0, 0, 0.560], atol=1e-12)
    np.testing.assert_allclose(pos["link4"], [0.0525, 0, 0.560], atol=1e-12)
    np.testing.assert_allclose(pos["link5"], [0.130, 0, 0.2175], atol=1e-12)
    np.testing.assert_allclose(pos["link7"], [0.206, 0, 0.1205], atol=1e-12)
    np.testing.assert_allclose(t[arm.link_index("link7"), :3, :3], DOWN, atol=1e-12)
    # gripper tcp 0.13 m along the flange z (down); fingers closed (q_g = 0) -> opening 0.
    np.testing.assert_allclose(arm.ee_pose(q)[:3, 3], [0.206, 0, 0.1205 - 0.13], atol=1e-12)
    assert arm.gripper_opening(q) == 0.0


def test_fk_at_known_joint_angles(arm):
    q = np.zeros(arm.n_q)
    # joint1 = +90 deg: the whole arm turns about world z; flange (0.206, 0, .1205) -> (0, 0.206, .1205).
    q1 = q.copy()
    q1[0] = np.pi / 2
    np.testing.assert_allclose(arm.link_pose(q1, "link7")[:3, 3], [0, 0.206, 0.1205], atol=1e-12)
    # joint2 = +90 deg: rotation about world +y through (0, 0, 0.267). Flange offset from the pivot
    # (0.206, 0, -0.1465) -> (-0.1465, 0, -0.206): flange at (-0.1465, 0, 0.061).
    q2 = q.copy()
    q2[1] = np.pi / 2
    t2 = arm.link_pose(q2, "link7")
    np.testing.assert_allclose(t2[:3, 3], [-0.1465, 0, 0.061], atol=1e-12)
    np.testing.assert_allclose(t2[:3, :3], _rot_y(np.pi / 2) @ DOWN, atol=1e-12)
    # joint4 = +90 deg: its axis is world -y through (0.0525, 0, 0.560). Flange offset
    # (0.1535, 0, -0.4395) rotated by -90 deg about +y -> (0.4395, 0, 0.1535): flange (0.492, 0, 0.7135).
    q4 = q.copy()
    q4[3] = np.pi / 2
    t4 = arm.link_pose(q4, "link7")
    np.testing.assert_allclose(t4[:3, 3], [0.492, 0, 0.7135], atol=1e-12)
    np.testing.assert_allclose(t4[:3, :3], _rot_y(-np.pi / 2) @ DOWN, atol=1e-12)


def test_batched_fk_equals_single(arm):
    rng = np.random.default_rng(0)
    qs = rng.uniform(arm.lower.clip(-3, 3), arm.upper.clip(-3, 3), size=(16, arm.n_q))
    batch = arm.fk(qs)
    assert batch.shape == (16, arm.n_links, 4, 4)
    for i in (0, 7, 15):
        np.testing.assert_allclose(batch[i], arm.fk(qs[i]), atol=1e-14)


def test_remembered_fk_is_fresh_and_owned_by_the_caller(arm):
    """fk remembers recent configurations: a remembered answer equals a fresh computation, a caller that
    edits its result does not change later answers, and a new configuration is computed anew."""
    rng = np.random.default_rng(1)
    qs = rng.uniform(arm.lower.clip(-3, 3), arm.upper.clip(-3, 3), size=(4, arm.n_q))
    fresh = arm._fk(qs)[0]
    first = arm.fk(qs)
    first[:] = 0.0  # the caller's copy
    for i in range(4):
        np.testing.assert_array_equal(arm.fk(qs[i]), fresh[i])
    np.testing.assert_array_equal(arm.fk(qs[[2, 0]]), fresh[[2, 0]])
    moved = qs[1] + 1e-3
    np.testing.assert_array_equal(arm.fk(moved), arm._fk(moved[None])[0][0])
    assert not np.array_equal(arm.fk(moved), fresh[1])


def test_jacobian_matches_finite_differences(arm):
    rng = np.random.default_rng(1)
    q = rng.uniform(-1.0, 1.0, size=arm.n_q)
    q[7] = 0.02
    ee, jac = arm.ee_pose_and_jacobian(q[None])
    eps = 1e-6
    for k, qi in enumerate(arm.arm_q_indices):
        dq = np.zeros(arm.n_q)
        dq[qi] = eps
        tp, tm = arm.ee_pose(q + dq), arm.ee_pose(q - dq)
        lin = (tp[:3, 3] - tm[:3, 3]) / (2 * eps)
        dr = (tp[:3, :3] - tm[:3, :3]) / (2 * eps) @ ee[0, :3, :3].T  # skew(omega)
        ang = np.array([dr[2, 1], dr[0, 2], dr[1, 0]])
        np.testing.assert_allclose(jac[0, :3, k], lin, atol=1e-7)
        np.testing.assert_allclose(jac[0, 3:, k], ang, atol=1e-7)


def test_mimic_fingers_open_symmetrically_to_85mm(arm):
    assert arm.joint("right_finger_joint").mimic == ("left_finger_joint", 1.0, 0.0)
    for closedness, gap in ((0.0, 0.085), (0.5, 0.0425), (1.0, 0.0)):
        q = arm.set_gripper(arm.home_q, closedness)
        base_inv = invert_pose(arm.link_pose(q, "gripper_base"))
        left = trimesh.transform_points(arm.contact_vertices(q, "left_finger"), base_inv)
        right = trimesh.transform_points(arm.contact_vertices(q, "right_finger"), base_inv)
        # inner faces: left finger's smallest y, right finger's largest y (gripper_base frame)
        assert left[:, 1].min() - right[:, 1].max() == pytest.approx(gap, abs=1e-12)
        assert arm.gripper_opening(q) == pytest.approx(gap, abs=1e-12)
        assert left[:, 1].min() == pytest.approx(-right[:, 1].max(), abs=1e-12)


def test_contact_mesh_interpolation_matches_fk_of_interpolated_q(arm):
    q0 = arm.set_gripper(arm.home_q, 0.0)
    q1 = arm.set_gripper(arm.home_q + np.r_[0.2, -0.1, 0.1, 0.3, -0.2, 0.1, 0.5, 0.0], 1.0)
    mid = arm.interpolate(q0, q1, 0.25)
    np.testing.assert_allclose(mid, 0.75 * q0 + 0.25 * q1)
    v = arm.contact_vertices_interpolated(q0, q1, 0.25, "left_finger")
    t = arm.link_pose(mid, "left_finger")
    local = np.asarray(arm.collision_meshes["left_finger"].vertices)
    np.testing.assert_allclose(v, local @ t[:3, :3].T + t[:3, 3], atol=1e-14)
    np.testing.assert_array_equal(arm.contact_faces("left_finger"), arm.collision_meshes["left_finger"].faces)
    # batched alphas give one vertex set per alpha; alpha 0 and 1 reproduce the end configurations
    vb = arm.contact_vertices_interpolated(q0, q1, np.array([0.0, 1.0]), "right_finger")
    np.testing.assert_allclose(vb[0], arm.contact_vertices(q0, "right_finger"), atol=1e-14)
    np.testing.assert_allclose(vb[1], arm.contact_vertices(q1, "right_finger"), atol=1e-14)


def test_pusher_tool(pusher_arm):
    assert pusher_arm.contact_links == ("pusher",)
    assert pusher_arm.gripper_joint is None and pusher_arm.n_q == 7
    # tcp = rod tip, 0.15 m below the flange at q = 0
    np.testing.assert_allclose(pusher_arm.ee_pose(np.zeros(7))[:3, 3], [0.206, 0, 0.1205 - 0.15], atol=1e-12)
    v = pusher_arm.contact_vertices(pusher_arm.home_q, "pusher")
    np.testing.assert_allclose(v[:, 2].min(), pusher_arm.ee_pose(pusher_arm.home_q)[2, 3], atol=1e-9)


# --------------------------------------------------------------------------- loading and errors
URDF_TEMPLATE = """<?xml version="1.0"?>
<robot name="tiny">
  <link name="base"/>
  <link name="finger_x">
    <visual><geometry><mesh filename="{mesh}"/></geometry></visual>
  </link>
  <joint name="slide" type="prismatic">
    <parent link="base"/><child link="finger_x"/>
    <origin xyz="0 0 0.1" rpy="0 0 0"/><axis xyz="1 0 0"/>
    <limit lower="0" upper="0.05" effort="1" velocity="1"/>
  </joint>
</robot>
"""


def _box_stl(path):
    path.parent.mkdir(parents=True, exist_ok=True)
    trimesh.creation.box(extents=(0.01, 0.02, 0.03)).export(path)


def test_package_paths_resolved_from_urdf_parents_and_package_dirs(tmp_path):
    _box_stl(tmp_path / "my_pkg" / "meshes" / "box.stl")
    urdf = tmp_path / "my_pkg" / "urdf" / "tiny.urdf"
    urdf.parent.mkdir()
    urdf.write_text(URDF_TEMPLATE.format(mesh="package://my_pkg/meshes/box.stl"))
    m = load_robot(urdf)
    assert m.joint_names == ["slide"] and m.ee_link == "finger_x"
    np.testing.assert_allclose(m.visual_meshes["finger_x"].extents, [0.01, 0.02, 0.03])
    np.testing.assert_allclose(m.ee_pose(np.array([0.03]))[:3, 3], [0.03, 0, 0.1])
    # URDF outside the package tree: only an explicit package dir finds the mesh
    _box_stl(tmp_path / "pkgs" / "other_pkg" / "meshes" / "box.stl")
    other = tmp_path / "elsewhere" / "tiny.urdf"
    other.parent.mkdir()
    other.write_text(URDF_TEMPLATE.format(mesh="package://other_pkg/meshes/box.stl"))
    with pytest.raises(FileNotFoundError, match="finger_x"):
        load_robot(other)
    m2 = load_robot(other, package_dirs=[tmp_path / "pkgs"])
    np.testing.assert_allclose(m2.visual_meshes["finger_x"].extents, [0.01, 0.02, 0.03])


def test_a_description_copied_out_of_its_package_finds_its_meshes(tmp_path):
    # example-robot-data's SO-101: package://example-robot-data/robots/so_arm_description/meshes/...,
    # with so_arm_description/ copied on its own (urdf/ and meshes/ side by side)
    _box_stl(tmp_path / "so_arm_description" / "meshes" / "so101" / "box.stl")
    urdf = tmp_path / "so_arm_description" / "urdf" / "tiny.urdf"
    urdf.parent.mkdir()
    urdf.write_text(URDF_TEMPLATE.format(
        mesh="package://example-robot-data/robots/so_arm_description/meshes/so101/box.stl"))
    np.testing.assert_allclose(load_robot(urdf).visual_meshes["finger_x"].extents, [0.01, 0.02, 0.03])
    # only tails of a folder and a file: a bare file name elsewhere is not taken for the mesh
    _box_stl(tmp_path / "other" / "box.stl")
    lone = tmp_path / "other" / "tiny.urdf"
    lone.write_text(URDF_TEMPLATE.format(mesh="package://pkg/meshes/gone/box.stl"))
    with pytest.raises(FileNotFoundError, match="ROS_PACKAGE_PATH=DIR"):
        load_robot(lone)


def test_missing_mesh_error_names_link_and_path(tmp_path):
    urdf = tmp_path / "tiny.urdf"
    urdf.write_text(URDF_TEMPLATE.format(mesh="meshes/nothing_here.stl"))
    with pytest.raises(FileNotFoundError) as err:
        load_robot(urdf)
    msg = str(err.value)
    assert "finger_x" in msg and "meshes/nothing_here.stl" in msg and str(urdf) in msg
    # without meshes the kinematics still load
    assert load_robot(urdf, load_meshes=False).joint_names == ["slide"]


def test_bad_urdf_path_and_content_errors(tmp_path):
    missing = tmp_path / "no_such_robot.urdf"
    with pytest.raises(FileNotFoundError, match="no_such_robot.urdf"):
        load_robot(missing)
    broken = tmp_path / "broken.urdf"
    broken.write_text("<robot name='x'><link name='a'></robot")
    with pytest.raises(URDFError, match="broken.urdf"):
        load_robot(broken)
    no_limit = tmp_path / "nolimit.urdf"
    no_limit.write_text(
        URDF_TEMPLATE.format(mesh="x.stl").replace(
            '<limit lower="0" upper="0.05" effort="1" velocity="1"/>', ""
        )
    )
    with pytest.raises(URDFError, match="slide"):
        load_robot(no_limit, load_meshes=False)


def test_bad_configuration_input(arm):
    with pytest.raises(ValueError, match="expected shape"):
        arm.fk(np.zeros(3))
    bad = arm.home_q.copy()
    bad[2] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        arm.fk(bad)


def test_contact_mesh_frames_for_the_physics_engine(arm):
    q0 = arm.set_gripper(arm.home_q, 0.0)
    q1 = arm.set_gripper(arm.home_q + 0.1, 0.7)
    frames = arm.contact_mesh_frames(q0, q1)
    assert set(frames) == {"left_finger", "right_finger"}
    for link, (v0, v1) in frames.items():
        np.testing.assert_allclose(v0, arm.contact_vertices(q0, link), atol=1e-14)
        np.testing.assert_allclose(v1, arm.contact_vertices(q1, link), atol=1e-14)


def test_contact_meshes_are_closed_for_signed_distance(arm, pusher_arm):
    # The physics engine queries signed distance to these meshes: they must be watertight and
    # consistently wound with outward normals (positive volume).
    for model in (arm, pusher_arm):
        for link in model.contact_links:
            mesh = model.collision_meshes[link]
            assert mesh.is_watertight and mesh.is_winding_consistent, link
            assert mesh.volume > 0, link
    fx, fy, fz = 0.02, 0.01, 0.06
    assert arm.collision_meshes["left_finger"].volume == pytest.approx(fx * fy * fz, rel=1e-6)


def test_fixed_links_are_those_no_joint_moves(tmp_path):
    """`fixed_links`: the root and links fixed to it by fixed joints only; a fixed joint below a moving one
    moves with it. Checked against FK: exactly the fixed links keep their pose over random q."""
    urdf = tmp_path / "chain.urdf"
    link = '<link name="{}"/>'
    joint = ('<joint name="{0}" type="{1}"><parent link="{2}"/><child link="{3}"/>'
             '<origin xyz="0.1 0 0.2" rpy="0.3 0 0"/><axis xyz="0 0 1"/>'
             '<limit lower="-1" upper="1" effort="1" velocity="1"/></joint>')
    links = "".join(link.format(n) for n in ("base", "pedestal", "arm", "tool", "cam"))
    joints = [("j0", "fixed", "base", "pedestal"), ("j1", "revolute", "pedestal", "arm"),
              ("j2", "fixed", "arm", "tool"), ("j3", "fixed", "base", "cam")]
    urdf.write_text('<robot name="chain">' + links + "".join(joint.format(*j) for j in joints) + "</robot>")
    m = load_robot(urdf, load_meshes=False)
    fixed = dict(zip(m.link_names, m.fixed_links, strict=True))
    assert fixed == {"base": True, "pedestal": True, "arm": False, "tool": False, "cam": True}
    poses = m.fk(np.random.default_rng(0).uniform(-1, 1, size=(6, m.n_q)))
    moved = np.abs(poses - poses[:1]).max(axis=(0, 2, 3)) > 1e-9
    np.testing.assert_array_equal(moved, ~m.fixed_links)


def _joint(name, kind, parent, child, xyz="0 0 0.1", extra=""):
    limit = '<limit lower="0" upper="0.04" effort="1" velocity="1"/>' if kind != "fixed" else ""
    return (f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
            f'<origin xyz="{xyz}" rpy="0 0 0"/><axis xyz="0 1 0"/>{limit}{extra}</joint>')


def _urdf(tmp_path, joints, name="r"):
    links = sorted({x for j in joints for x in (j.split('link="')[1].split('"')[0],
                                                  j.split('link="')[2].split('"')[0])})
    body = "".join(f'<link name="{n}"/>' for n in links) + "".join(joints)
    path = tmp_path / f"{name}.urdf"
    path.write_text(f'<?xml version="1.0"?><robot name="{name}">{body}</robot>')
    return path


def test_the_default_end_effector_is_the_deepest_link_not_on_a_finger(tmp_path):
    arm = [_joint("j1", "revolute", "base", "l1"), _joint("j2", "revolute", "l1", "l2"),
           _joint("to_hand", "fixed", "l2", "hand")]
    # Panda's ending: two fingers (one mimics the other) and a fixed TCP link, all at one depth, the
    # fingers first in the file (the old rule, the first deepest link, picked a finger and put its joint
    # into the IK chain)
    panda = arm + [_joint("f1", "prismatic", "hand", "left"),
                   _joint("f2", "prismatic", "hand", "right", extra='<mimic joint="f1"/>'),
                   _joint("to_tcp", "fixed", "hand", "tcp", xyz="0 0 0.1")]
    m = load_robot(_urdf(tmp_path, panda, "panda_like"))
    assert m.ee_link == "tcp" and m.arm_joints == ["j1", "j2"]
    # two fingers without mimic, deeper than the hand: still not the end effector
    m = load_robot(_urdf(tmp_path, arm + [_joint("f1", "prismatic", "hand", "left"),
                                          _joint("f2", "prismatic", "hand", "right")], "two_fingers"))
    assert m.ee_link == "hand" and m.arm_joints == ["j1", "j2"]
    # one jaw: a finger only when named as the gripper joint
    jaw = arm + [_joint("jaw", "prismatic", "hand", "jaw_link")]
    assert load_robot(_urdf(tmp_path, jaw, "one_jaw")).ee_link == "jaw_link"
    assert load_robot(_urdf(tmp_path, jaw, "one_jaw"), gripper_joint="jaw").ee_link == "hand"
    # two arms branching at a torso are not fingers (their joints have moving joints below them)
    two = [_joint("la1", "revolute", "torso", "la"), _joint("la2", "revolute", "la", "lh"),
           _joint("ra1", "revolute", "torso", "ra"), _joint("ra2", "revolute", "ra", "rh")]
    m = load_robot(_urdf(tmp_path, two, "two_arms"))
    assert m.ee_link == "lh" and m.arm_joints == ["la1", "la2"]
    # an explicit ee_link is kept
    assert load_robot(_urdf(tmp_path, panda, "panda_like"), ee_link="left").arm_joints == ["j1", "j2", "f1"]


def test_a_heavy_convex_contact_mesh_is_simplified_inside_its_hull_by_the_distance_it_reports():
    """A 20,480-face sphere: its simplified hull has at most the asked faces, is convex, lies inside the
    exact hull, and every exact-hull point is within the reported distance of it (the distance is the
    Hausdorff distance: one vertex attains it)."""
    from twinbench.robot.model import convex_contact_mesh

    ball = trimesh.creation.icosphere(subdivisions=5, radius=0.02)
    small, moved = convex_contact_mesh(ball, max_faces=300)
    assert len(small.faces) <= 300 and small.is_convex and small.is_watertight
    assert 0 < moved < 0.002  # a 2 cm ball, a few hundred faces: well under 2 mm
    assert np.all(np.linalg.norm(small.vertices, axis=1) <= 0.02 + 1e-9)  # its vertices are the ball's
    _, dist, _ = trimesh.proximity.closest_point(small, ball.vertices)
    assert dist.max() == pytest.approx(moved, rel=1e-9)
    assert small.volume < ball.volume and small.volume > ball.volume * (1 - 3 * moved / 0.02)
    # a mesh small enough keeps its exact hull; a flat one has none
    box = trimesh.creation.box((0.01, 0.02, 0.03))
    hull, moved = convex_contact_mesh(box)
    assert moved == 0.0 and hull.volume == pytest.approx(6e-6) and len(hull.faces) == 12
    with pytest.raises(ValueError, match="flat"):
        square = trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], [[0, 1, 2], [1, 3, 2]])
        convex_contact_mesh(square)


def test_with_convex_contacts_replaces_only_the_contact_links_meshes(tmp_path):
    """A C-shaped jaw (concave) collides through its hull, which fills the jaw's mouth; other links keep
    their meshes; the original model is unchanged; a flat contact mesh is an error naming the link."""
    back = trimesh.creation.box((0.01, 0.05, 0.01))
    top = trimesh.creation.box((0.04, 0.01, 0.01))
    top.apply_translation((0.015, 0.02, 0))
    bottom = top.copy()
    bottom.apply_translation((0, -0.04, 0))
    trimesh.util.concatenate([back, top, bottom]).export(tmp_path / "jaw.stl")
    trimesh.creation.box((0.1, 0.1, 0.1)).export(tmp_path / "base.stl")
    (tmp_path / "arm.urdf").write_text(
        '<robot name="arm"><link name="base"><collision><geometry><mesh filename="base.stl"/></geometry>'
        '</collision></link><link name="jaw"><collision><geometry><mesh filename="jaw.stl"/></geometry>'
        '</collision></link><joint name="z" type="prismatic"><parent link="base"/><child link="jaw"/>'
        '<axis xyz="0 0 1"/><limit lower="0" upper="0.3" effort="1" velocity="1"/></joint></robot>')
    model = load_robot(tmp_path / "arm.urdf", contact_links=("jaw",))
    convex = model.with_convex_contacts()
    jaw = convex.collision_meshes["jaw"]
    assert jaw.is_convex and jaw.volume == pytest.approx(0.04 * 0.05 * 0.01)  # the mouth filled
    assert model.collision_meshes["jaw"].volume == pytest.approx(2 * 0.04 * 0.01 * 0.01 + 0.01 * 0.05 * 0.01)
    inside_mouth = np.array([[0.02, 0.0, 0.0]])
    assert jaw.contains(inside_mouth)[0] and not model.collision_meshes["jaw"].contains(inside_mouth)[0]
    assert convex.collision_meshes["base"] is model.collision_meshes["base"]
    assert convex.convex_contact_moved == {"jaw": 0.0} and model.convex_contact_moved == {}
    np.testing.assert_allclose(convex.contact_vertices(np.array([0.1]), "jaw")[:, 2].max(), 0.105)
    trimesh.Trimesh([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0]], [[0, 1, 2]]).export(tmp_path / "jaw.stl")
    flat = load_robot(tmp_path / "arm.urdf", contact_links=("jaw",))
    with pytest.raises(URDFError, match=r"arm.urdf: contact link 'jaw': its collision mesh is flat"):
        flat.with_convex_contacts()
