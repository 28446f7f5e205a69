"""The study on rope routing: the reconstruction's pieces for a rope (its marked end told apart by colour)
and a fixed collider (the clip: mesh, pose from the scan, channel), the rope perception controller's
estimate against the true rope (known answers), the refusals for tasks without perception controllers, and
(slow) a tiny study end to end on a hidden real rope workcell."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest

from twinbench.errors import InputError
from twinbench.study import policies as P
from twinbench.study.reconstruct import estimate_rest_pose, place_collider
from twinbench.transforms import planar_pose, rotation_angle, transform_points
from twinbench.twin.cells import rope_routing_cell

# the rope estimate from the fast cell's front image (120 x 212 px, ~5 mm a pixel on the table), measured on
# states 4, 13, 20: end <= 10 mm, the point 4 cm along <= 8 mm, centroid <= 23 mm (the gripper hides part of
# the rope)
END_TOL_M, ALONG_TOL_M, CENTROID_TOL_M = 0.015, 0.015, 0.035


def _yaw(pose) -> float:
    return float(np.arctan2(pose[1, 0], pose[0, 0]))


def _scan_colours(rgb, seed: int):
    """`rgb` in a scanner's colour space (a degree-2 colour map, as the study's scans)."""
    from twinbench.gaussians.colormap import map_colors
    from twinbench.study.real import _scan_color_space

    return np.clip(map_colors(rgb, _scan_color_space(np.random.default_rng(seed)), 2), 0, 1)


@pytest.mark.parametrize("yaw_deg", [20.0, 200.0, -95.0])
def test_rest_pose_tells_the_rope_ends_apart_by_colour(yaw_deg):
    """A straight tube fits its scan equally well both ways round: the marked end's colour decides."""
    rope = rope_routing_cell("fast").objects[0]
    g = rope.gaussians
    rng = np.random.default_rng(int(yaw_deg) % 7)
    truth = planar_pose(0.33, 0.02, np.radians(yaw_deg))
    keep = rng.random(len(g)) < 0.5
    seen = transform_points(truth, g.means[keep].astype(np.float64)) + rng.normal(0, 0.0015, (keep.sum(), 3))
    pose = estimate_rest_pose(seen, g.means, 0.0, _scan_colours(g.base_colours[keep], 3), g.base_colours)
    assert np.linalg.norm(pose[:2, 3] - truth[:2, 3]) < 0.003
    assert np.degrees(rotation_angle(pose[:3, :3], truth[:3, :3])) < 2.0  # not half a turn off


@pytest.mark.parametrize("turn", [0.0, np.pi])
def test_clip_pose_from_its_scan(turn):
    """The clip registered to its scan Gaussians; of its two equal poses (a half turn apart: the same walls
    and channel) the one nearer the cell's declared heading."""
    clip = rope_routing_cell("fast").colliders[0]
    rng = np.random.default_rng(1)
    truth = planar_pose(0.615, 0.058, np.radians(3.0))
    placed = truth @ planar_pose(0.0, 0.0, turn)  # the scan cannot tell these apart
    keep = rng.random(len(clip.gaussians)) < 0.5
    seen = transform_points(placed, clip.gaussians.means[keep].astype(np.float64))
    seen += rng.normal(0, 0.0015, seen.shape)
    pose = place_collider(seen, clip)
    assert np.linalg.norm(pose[:2, 3] - truth[:2, 3]) < 0.002
    assert abs(np.degrees(_yaw(pose) - _yaw(truth))) < 3.0  # measured 1.6: 3.5 cm walls


def test_build_config_collider_channel_and_colour_map(tmp_path):
    import trimesh

    from twinbench.construct.build_config import build_spec_from_config
    from twinbench.gaussians.colormap import identity_color_map
    from twinbench.twin import save_object

    cell = rope_routing_cell("fast")
    clip = cell.colliders[0]
    save_object(cell.objects[0], tmp_path / "rope")
    trimesh.Trimesh(clip.vertices, clip.faces, process=False).export(tmp_path / "clip.obj")
    cmap = identity_color_map(2)
    cmap[:, 0] = 0.1
    (tmp_path / "cmap.json").write_text(json.dumps({"degree": 2, "coeffs": cmap.tolist()}))
    (tmp_path / "cal.json").write_text(json.dumps({"cameras": [{
        "name": "front", "intrinsics": [200.0, 200.0, 106.0, 60.0], "sensor_size": [212, 120],
        "output_hw": [120, 212], "camera_to_world": np.eye(4).tolist()}]}))
    config = {"name": "rope", "robot": {"urdf": "builtin:xarm7_gripper"}, "objects": [{"dir": "rope"}],
              "colliders": [{"name": "clip", "mesh": "clip.obj", "pose": clip.pose.tolist(), "friction": 0.7,
                             "channel": [0.035, 0.03, 0.035], "color_map": "cmap.json"}],
              "cameras": "cal.json"}
    (tmp_path / "build.json").write_text(json.dumps(config))
    spec = build_spec_from_config(tmp_path / "build.json")
    c = spec.colliders[0]
    assert c.channel == (0.035, 0.03, 0.035) and c.contact.friction == 0.7
    assert np.allclose(c.color_map.coeffs, cmap) and np.allclose(c.vertices, clip.vertices)


def test_rebuilt_robot_commands_the_cells_end_effector(tmp_path):
    """The build config's robot carries the cell's control conventions: a rope twin rebuilt without them
    read every action as the TCP's pose where the real workcell reads the flange's (replayed real actions
    never grasped)."""
    from twinbench.construct.build_config import build_spec_from_config
    from twinbench.study.reconstruct import robot_entry

    cell = rope_routing_cell("fast")
    assert cell.robot.ee_link == "link7"
    (tmp_path / "cal.json").write_text(json.dumps({"cameras": [{
        "name": "front", "intrinsics": [200.0, 200.0, 106.0, 60.0], "sensor_size": [212, 120],
        "output_hw": [120, 212], "camera_to_world": np.eye(4).tolist()}]}))
    from twinbench.twin import save_object

    save_object(cell.objects[0], tmp_path / "rope")
    robot = {k: v for k, v in robot_entry(cell.robot, None).items() if k != "aligned"}
    config = {"name": "rope", "robot": {"urdf": cell.robot.urdf, **robot}, "objects": [{"dir": "rope"}],
              "cameras": "cal.json"}
    (tmp_path / "build.json").write_text(json.dumps(config))
    spec = build_spec_from_config(tmp_path / "build.json")
    for k in ("ee_link", "contact_links", "gripper_joint", "gripper_open", "gripper_closed", "home_q"):
        assert getattr(spec.robot, k) == getattr(cell.robot, k), k
    assert spec.robot.tool_contact == cell.robot.tool_contact


@pytest.fixture(scope="module")
def rope_scene():
    """The fast rope cell's env, its front camera, and per grid state the front image and the true
    environment_state."""
    from twinbench.tasks import get_task

    env = get_task("rope-routing").make_env(preset="fast", environment_state=True, cameras="front")
    u = env.unwrapped
    cam = u.twin.camera(u.state, "front")
    table = P.table_mask(cam, *P._rope_workspace(u))
    frames, labels = {}, {}
    for i in (0, 4, 13, 20, 26):
        obs, _ = env.reset(seed=0, options={"init_state": i})
        frames[i] = (obs["pixels"]["front"], np.asarray(obs["environment_state"], np.float64))
        labels[i] = P.rope_labels(u, cam, table)
    yield u, cam, frames, labels
    env.close()


def test_rope_estimate_from_the_front_image_matches_the_true_rope(rope_scene):
    u, cam, frames, labels = rope_scene
    samples: dict = {}
    for i in (0, 26):  # the colour model from two labelled images
        for region, mask in labels[i].items():
            samples.setdefault(region, []).append(frames[i][0][mask])
    colors = P.fit_colors(samples, ("rope", "mark", "table"))
    est = P.RopeEstimator(cam, colors, P.CHI2_3_999, 20, *P._rope_workspace(u))
    for i in (4, 13, 20):  # states the colours were not fitted on
        img, s = frames[i]
        got = est.estimate(img)
        assert got is not None, i
        errors = [np.linalg.norm(got[k:k + 2] - s[k:k + 2]) for k in (0, 3, 6)]
        print(f"state {i}: end {errors[0]:.4f} m, along {errors[1]:.4f} m, centroid {errors[2]:.4f} m")
        assert errors[0] < END_TOL_M and errors[1] < ALONG_TOL_M and errors[2] < CENTROID_TOL_M, (i, errors)


def test_tasks_without_perception_controllers_are_refused(tmp_path):
    from twinbench.study.evaluate import make_policies

    with pytest.raises(InputError, match="point-reach"):
        make_policies("point-reach", tmp_path / "real", tmp_path / "policies")
    with pytest.raises(InputError, match="point-reach"):
        P.levels({}, None, "point-reach")
    for task in ("push-t", "rope-routing", "toy-packing"):
        assert set(P.levels({}, None, task)) == set(P.LEVELS[task])
    assert not (tmp_path / "policies").exists()
    from twinbench.cli import main as cli_main

    assert cli_main(["study", "run", "--out", str(tmp_path / "study"), "--task", "point-reach"]) == 2
    assert not (tmp_path / "study").exists()  # refused before any stage


@pytest.mark.slow
@pytest.mark.timeout(2400)
def test_tiny_rope_study_end_to_end(tmp_path, monkeypatch):
    """make-real -> evidence -> reconstruct (REAL/ moved away, its hidden file deleted) -> policies ->
    evaluation in the real workcell and the rebuilt twin, on a tiny size (1 grid state, 1 s episodes,
    short probe motion, a small sysid budget)."""
    from twinbench.evaluation.store import ResultsStore
    from twinbench.policies import spec as spec_module
    from twinbench.study import evaluate as E
    from twinbench.study.evidence import make_evidence
    from twinbench.study.real import make_real
    from twinbench.study.reconstruct import reconstruct
    from twinbench.tasks import get_task
    from twinbench.twin import load_twin

    tiny = E.StudySize((0,), 1.0, 2, motion_frames=(24, 6))
    real = make_real("rope-routing", 1, tmp_path / "REAL", tiny)
    ev = make_evidence(real, tmp_path / "EV", seed=1, size=tiny)
    assert json.loads((ev / "evidence.json").read_text())["colliders"] == ["clip"]
    hidden = json.loads((real / "hidden.json").read_text())
    real_spec = load_twin(real / "world")
    (real / "hidden.json").unlink()
    shutil.move(real, tmp_path / "elsewhere")  # the reconstruction cannot open REAL/
    lines: list[str] = []
    twins = reconstruct(ev, tmp_path / "TW", variants=("full", "no-physics"), log=lines.append,
                        sysid_args=("--cma.budget", "12", "--adam.epochs", "2"))
    shutil.move(tmp_path / "elsewhere", real)
    work = tmp_path / "TW/construction"
    assert any(ln.startswith("# collider clip: pose from the scan") for ln in lines)

    # the robot's pose: align-robot's transform composed with the user's coarse one undoes the scan's frame
    coarse = np.asarray(json.loads((ev / "boxes.json").read_text())["transform"])
    found = np.asarray(json.loads((work / "aligned/report.json").read_text())["transform"])
    err = found @ coarse @ np.asarray(hidden["scan"]["world_to_scan"])
    assert np.degrees(rotation_angle(err[:3, :3], np.eye(3))) < 0.3 and np.linalg.norm(err[:3, 3]) < 0.003
    # sysid lowers the tracking error on the evidence
    report = json.loads((work / "sysid/fitted/sysid_report.json").read_text())["evaluations"]
    assert report["final"]["train_error_m"] < report["initial"]["train_error_m"]

    # the rebuilt twin: its clip where the real one is, with its channel; the rope's marked end where the
    # real one's is (the scan's colours decide which end); the expert runs on it
    spec = load_twin(twins["full"])
    clip, real_clip = spec.colliders[0], real_spec.colliders[0]
    assert clip.name == "clip" and clip.channel == real_clip.channel and clip.color_map is not None
    assert np.linalg.norm(clip.pose[:2, 3] - real_clip.pose[:2, 3]) < 0.003
    assert abs(np.degrees(_yaw(clip.pose) - _yaw(real_clip.pose))) < 1.5
    states = {}
    for name, world in (("twin", twins["full"]), ("real", real / "world")):
        env = get_task("rope-routing").make_env(twin=str(world), environment_state=True, cameras="",
                                                episode_seconds=1.0)
        obs, _ = env.reset(seed=0, options={"init_state": 0})
        states[name] = np.asarray(obs["environment_state"], np.float64)
        if name == "twin":
            expert = get_task("rope-routing").make_expert(env)
            for _ in range(5):
                obs, *_ = env.step(expert.select_action(obs))
            assert expert.phase == "approach"
        env.close()
    assert np.linalg.norm(states["twin"][:2] - states["real"][:2]) < 0.01  # the marked end
    assert np.allclose(states["twin"][9:12], states["real"][9:12], atol=0.02)  # the clip's x, y, theta

    # perception policies calibrated on the real workcell, evaluated there and in the twins
    monkeypatch.setattr(spec_module, "POLICY_KINDS", dict(spec_module.POLICY_KINDS))  # evaluate adds perceive
    policies = E.make_policies("rope-routing", real / "world", tmp_path / "policies", tiny,
                               E.user_calibration(ev),
                               names=("r0-clean", "r6-noise4cm"))
    assert len(policies) == 2
    E.run_evaluations("rope-routing", real / "world", {"full": twins["full"]}, policies, tmp_path, tiny)
    doc = E.write_study_json(tmp_path, "rope-routing", tiny, ["full"], {"evaluate": 1.0})
    store = ResultsStore(tmp_path / "results" / "results.sqlite")
    real_eps = store.episodes(E.REAL, domain="real")
    assert len(real_eps) == 2 and all(r.status == "ok" for r in real_eps)
    row = doc["variants"][0]
    sim_eps = {r.policy: r.success for r in store.episodes(E.twin_run_id("full"))}
    for d in row["policies"]:  # the table's rates are the store's
        assert d["sim"] == float(sim_eps[d["policy"]]) and d["n_sim"] == d["n_real"] == 1
        assert d["real"] == float(next(r.success for r in real_eps if r.policy == d["policy"]))
    assert row["mmrv"]["value"] is not None and row["replay"] is not None
