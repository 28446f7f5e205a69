"""The whole construction chain through the CLI, on a synthetic cell with hidden ground truth: a scan
made from the built-in push-T twin is moved, recoloured and made noisy; segment -> align-robot ->
align-color -> twin build rebuilds a twin whose front image matches the original's."""

from __future__ import annotations

import dataclasses
import json
import re

import imageio.v3 as iio
import numpy as np
import pytest

from twinbench.cli import main as cli
from twinbench.construct.calibration import calibration_doc
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.colormap import apply_color_map, identity_color_map
from twinbench.gaussians.io import save_gaussians
from twinbench.transforms import rotvec_to_matrix
from twinbench.twin import build_twin, load_twin, save_object
from twinbench.twin.build import _robot_gaussians, load_spec_robot
from twinbench.twin.cells import push_t_cell


@pytest.mark.timeout(300)
def test_chain_rebuilds_the_cell(tmp_path):
    spec = push_t_cell("fast")
    twin, state = build_twin(spec)
    original = twin.render(state, ["front"])["front"].rgb
    model = load_spec_robot(spec.robot)
    robot_world = _robot_gaussians(spec.robot, model).posed(model.home_q)
    block = spec.objects[0]
    world = GaussianCloud.concatenate(
        [robot_world, block.gaussians.transform(block.rest_pose), spec.background]
    )
    # the "phone scan": unknown frame, other colours, noisy positions
    rng = np.random.default_rng(0)
    true = np.eye(4)
    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    true[:3, :3] = rotvec_to_matrix(np.radians(25.0) * axis)
    true[:3, 3] = [0.2, -0.1, 0.15]
    hidden_map = identity_color_map(2)
    hidden_map[:, 0] = [0.04, -0.02, 0.03]
    hidden_map[:, 1:4] = np.diag([0.85, 0.95, 1.05])
    hidden_map[:, 4] = [0.08, 0.0, -0.05]
    scan = apply_color_map(world.transform(true), hidden_map, 2)
    scan.means += rng.normal(0, 0.001, scan.means.shape).astype(np.float32)
    save_gaussians(scan, tmp_path / "scan.ply")
    # the user's coarse transform (1 deg, 1 cm off) and boxes in that frame
    coarse = np.linalg.inv(true)
    off = np.eye(4)
    off[:3, :3] = rotvec_to_matrix(np.radians(1.0) * np.array([0.0, 0.6, 0.8]))
    off[:3, 3] = [0.01, -0.005, 0.004]
    boxes = {
        "transform": (off @ coarse).tolist(),
        "robot": {"center": [0.1, 0.0, 0.56], "half_extents": [0.32, 0.3, 0.52]},
        "objects": {"tblock": {"center": [*block.rest_pose[:2, 3], 0.02], "half_extents": [0.1, 0.1, 0.035]}},
    }
    (tmp_path / "boxes.json").write_text(json.dumps(boxes))
    assert cli(["segment", str(tmp_path / "scan.ply"), "--boxes", str(tmp_path / "boxes.json"),
                "--out", str(tmp_path / "seg")]) == 0
    assert cli(["align-robot", str(tmp_path / "seg/robot.ply"), "--urdf", spec.robot.urdf,
                "--out", str(tmp_path / "aligned"), "--also", str(tmp_path / "seg/background.ply"),
                str(tmp_path / "seg/objects/tblock.ply")]) == 0
    report = json.loads((tmp_path / "aligned/report.json").read_text())
    err = np.asarray(report["transform"]) @ off @ coarse @ true  # world -> world, identity when exact
    assert np.abs(err - np.eye(4)).max() < 3e-3
    # colour: render the aligned scan from the calibrated front camera beside the "real" image
    (tmp_path / "calibration.json").write_text(json.dumps(calibration_doc(spec.cameras)))
    (tmp_path / "real").mkdir()
    iio.imwrite(tmp_path / "real/front.png", (np.clip(original, 0, 1) * 255 + 0.5).astype(np.uint8))
    parts = [tmp_path / "aligned/robot.ply", tmp_path / "aligned/aligned/background.ply",
             tmp_path / "aligned/aligned/tblock.ply"]
    calib = str(tmp_path / "calibration.json")
    assert cli(["align-color", "--scan", *map(str, parts), "--calibration", calib,
                "--real", str(tmp_path / "real"), "--out", str(tmp_path / "color")]) == 0
    # the trained object twin (here: the cell's own T-block, without Gaussians: the scan gives them)
    save_object(dataclasses.replace(block, gaussians=None), tmp_path / "objects/tblock",
                sim={k: v for k, v in dataclasses.asdict(spec.sim).items()})
    config = {
        "name": "rebuilt",
        "robot": {"aligned": "aligned", "color_map": "color/color_map.json", "home_q": None,
                  "tool_contact": dataclasses.asdict(spec.robot.tool_contact)},
        "background": {"gaussians": "aligned/aligned/background.ply", "color_map": "color/color_map.json"},
        "objects": [{"dir": "objects/tblock", "rest_pose": block.rest_pose.tolist(),
                     "gaussians": "aligned/aligned/tblock.ply", "color_map": "color/color_map.json"}],
        "cameras": "calibration.json",
        "controller": {k: v for k, v in dataclasses.asdict(spec.controller).items()},
        "render": {"background": list(spec.render_background)},
    }
    config["robot"] = {k: v for k, v in config["robot"].items() if v is not None}
    (tmp_path / "build.json").write_text(json.dumps(config))
    assert cli(["twin", "build", str(tmp_path / "build.json"), "--out", str(tmp_path / "twin")]) == 0
    rebuilt = load_twin(tmp_path / "twin")
    twin2, state2 = build_twin(rebuilt)
    image = twin2.render(state2, ["front"])["front"].rgb
    err = np.abs(image - original).mean()
    print(f"mean abs image error {err:.4f}")
    assert err < 0.02, f"mean abs image error {err:.4f}"
    # without the colour map the images differ clearly (the test can fail)
    plain = build_twin(dataclasses.replace(rebuilt, background_color_map=None))
    assert np.abs(plain[0].render(plain[1], ["front"])["front"].rgb - original).mean() > 2 * err


def _users_arm_config(tmp_path, tip_link: str, axis: str, **robot) -> dict:
    """A build config (written to tmp_path/build.json) of a user's one-joint arm whose link `tip` (given
    as URDF) moves along `axis`, with push-T's block and one camera; `robot`: more robot fields."""
    (tmp_path / "arm.urdf").write_text(
        f'<robot name="arm"><link name="base"/>{tip_link}<joint name="j" type="prismatic">'
        f'<parent link="base"/><child link="tip"/><axis xyz="{axis}"/>'
        '<limit lower="0.1" upper="0.5" effort="1" velocity="1"/></joint></robot>')
    save_object(push_t_cell("fast").objects[0], tmp_path / "tblock")
    (tmp_path / "cal.json").write_text(json.dumps({"cameras": [{
        "name": "front", "intrinsics": [200.0, 200.0, 106.0, 60.0], "sensor_size": [212, 120],
        "output_hw": [120, 212], "camera_to_world": np.eye(4).tolist()}]}))
    config = {"robot": {"urdf": "arm.urdf", "contact_links": ["tip"], **robot},
              "objects": [{"dir": "tblock"}], "cameras": "cal.json"}
    (tmp_path / "build.json").write_text(json.dumps(config))
    return config


def test_build_config_gives_a_users_pusher_its_tool_radius(tmp_path):
    """A user's own URDF with a pushing tool: the build config carries the tip radius that push-T's rules
    read (the built-in pusher fills it in itself); before, the field was refused and the user had to edit
    twin.json by hand."""
    from twinbench.construct.build_config import build_spec_from_config

    config = _users_arm_config(tmp_path, '<link name="tip"/>', "1 0 0", tool_radius=0.0125)
    spec = build_spec_from_config(tmp_path / "build.json")
    assert spec.robot.tool_radius == 0.0125 and spec.robot.contact_links == ("tip",)
    config["robot"]["tip_radius"] = 0.01
    (tmp_path / "build.json").write_text(json.dumps(config))
    unknown = r"robot: unknown field\(s\) \['tip_radius'\]; known: .*'tool_radius'"
    with pytest.raises(ValueError, match=unknown):
        build_spec_from_config(tmp_path / "build.json")


def test_a_heavy_contact_mesh_collides_through_its_simplified_hull_when_the_config_asks(tmp_path, recwarn):
    """`robot.contact_mesh: "convex_hull"` in a build config: the twin's physics holds the tool's hull of
    at most 1,000 faces instead of its 20,480-face mesh (no slow-step warning), the twin directory keeps
    the choice, and `twin show`'s summary says how far the hull moved; a value it does not know is
    refused naming the field."""
    import trimesh

    from twinbench.commands.twin import summary
    from twinbench.construct.build_config import build_from_config, build_spec_from_config
    from twinbench.twin import save_twin

    trimesh.creation.icosphere(subdivisions=5, radius=0.02).export(tmp_path / "ball.stl")  # 20,480 faces
    tip = ('<link name="tip"><visual><geometry><sphere radius="0.02"/></geometry></visual><collision>'
           '<geometry><mesh filename="ball.stl"/></geometry></collision></link>')
    config = _users_arm_config(tmp_path, tip, "0 0 1", contact_mesh="convex_hull")
    spec = build_spec_from_config(tmp_path / "build.json")
    assert spec.robot.contact_mesh == "convex_hull"
    twin, _ = build_twin(load_twin(save_twin(spec, tmp_path / "twin").parent))
    assert not [w for w in recwarn.list if "faces" in str(w.message)]
    tool = twin.model.meshes[twin._tool_mesh["tip"]]
    assert 100 < len(tool.faces) <= 1000 and trimesh.Trimesh(tool.vertices, tool.faces).is_convex
    assert re.search(r"contact links \[tip \(\d{3} faces, convex hull within 0\.\d mm\)\]", summary(twin)[1])
    config["robot"]["contact_mesh"] = "hull"
    (tmp_path / "build.json").write_text(json.dumps(config))
    refused = r"robot.contact_mesh: expected one of \['collision', 'convex_hull'\], got 'hull'"
    with pytest.raises(ValueError, match=refused):
        build_spec_from_config(tmp_path / "build.json")
    del config["robot"]["contact_mesh"]  # the default: the mesh as it is, and twin.json without the field
    (tmp_path / "build.json").write_text(json.dumps(config))
    with pytest.warns(UserWarning, match='20,480 faces.*set robot.contact_mesh to "convex_hull"'):
        path = build_from_config(tmp_path / "build.json", tmp_path / "plain")  # said at build already
    assert "contact_mesh" not in json.loads(path.read_text())["robot"]
    # the robot's fields are checked against its URDF before anything is written
    config["robot"]["contact_links"] = ["tp"]
    (tmp_path / "build.json").write_text(json.dumps(config))
    with pytest.raises(ValueError, match=r"build.json: robot: .*arm.urdf: contact link 'tp' is not a link"):
        build_from_config(tmp_path / "build.json", tmp_path / "typo")
    assert not (tmp_path / "typo").exists()
