"""Twin directories: a lossless round trip, built-in vs exported twins giving bit-identical episodes, and
one clear error per malformed directory."""

import dataclasses
import json
import pickle
import shutil

import numpy as np
import pytest
import trimesh

from twinbench.commands.twin import ExportConfig, export
from twinbench.env import TwinEnv
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.colormap import identity_color_map
from twinbench.gaussians.primitives import surface_discs
from twinbench.robot.builtin import load_builtin_arm
from twinbench.robot.gaussians import sample_robot_scan
from twinbench.transforms import planar_pose
from twinbench.twin import (
    ColliderSpec,
    ColorMap,
    ContactSpec,
    ObjectSpec,
    RobotSpec,
    TwinFormatError,
    build_twin,
    load_object,
    load_twin,
    save_object,
    save_twin,
)
from twinbench.twin.build import load_spec_robot
from twinbench.twin.cells import front_camera, push_t_cell, rope_routing_cell, wrist_camera
from twinbench.twin.shapes import Outline


def assert_same(a, b, where="spec"):
    """Recursive equality of spec data: arrays bit for bit (dtype included), clouds field by field."""
    if isinstance(a, GaussianCloud):
        for f in ("means", "quats", "log_scales", "logit_opacities", "sh"):
            assert_same(getattr(a, f), getattr(b, f), f"{where}.{f}")
    elif dataclasses.is_dataclass(a):
        assert type(a) is type(b), where
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{where}.{f.name}")
    elif isinstance(a, np.ndarray):
        assert isinstance(b, np.ndarray) and a.dtype == b.dtype, (
            f"{where}: {a.dtype} vs {getattr(b, 'dtype', b)}"
        )
        np.testing.assert_array_equal(a, b, err_msg=where)
    elif isinstance(a, tuple | list):
        assert len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{where}[{i}]")
    else:
        assert a == b, f"{where}: {a!r} != {b!r}"


def _disc(n, rgb, seed=0):
    rng = np.random.default_rng(seed)
    return surface_discs(
        rng.uniform(-0.02, 0.02, (n, 3)).astype(np.float32), np.tile([0.0, 0, 1], (n, 1)), rgb, 0.004
    )


def _rich_spec():
    """A twin using every field: scanned robot Gaussians, explicit springs with per-spring Y and masses,
    a collider with Gaussians, colour maps, a crop box, depth."""
    model = load_builtin_arm("gripper")
    scan = sample_robot_scan(model, spacing=0.03)
    q = model.home_q.copy()
    q[0] += 0.2
    cmap = identity_color_map(2)
    cmap[0, 0] = 0.05
    rng = np.random.default_rng(1)
    pts = rng.uniform(-0.03, 0.03, (40, 3))
    springs = np.array([[i, j] for i in range(40) for j in range(i + 1, min(i + 4, 40))], np.int32)
    rope = ObjectSpec(
        "rope",
        pts,
        springs=springs,
        rest_lengths=np.linalg.norm(pts[springs[:, 0]] - pts[springs[:, 1]], axis=1).astype(np.float32),
        spring_Y=rng.uniform(1e3, 1e4, len(springs)),
        mass=rng.uniform(0.5, 2.0, 40),
        gaussians=_disc(30, (0.9, 0.8, 0.1)),
        binding="lbs",
        rest_pose=planar_pose(0.4, 0.1, 0.2),
        color_map=ColorMap(2, cmap),
    )
    block = ObjectSpec(
        "block",
        rng.uniform(-0.02, 0.02, (27, 3)).astype(np.float32),
        spring_radius=0.025,
        max_neighbors=12,
        spring_Y=2e4,
        gaussians=_disc(20, (0.2, 0.3, 0.8), 1),
        binding="rigid",
        rest_pose=planar_pose(0.5, -0.1, 0.0),
        outline=Outline(np.array([[-0.02, -0.02], [0.02, -0.02], [0.0, 0.03]]), 0.02),
    )
    box = trimesh.creation.box(extents=(0.1, 0.12, 0.05))
    box.vertices += rng.normal(0, 1e-4, box.vertices.shape)
    collider = ColliderSpec(
        "box",
        np.asarray(box.vertices),
        np.asarray(box.faces),
        planar_pose(0.55, 0.2, 0.3),
        ContactSpec(0.1, 0.7),
        _disc(15, (0.4, 0.4, 0.4), 2),
        ColorMap(1, identity_color_map(1)),
        channel=(0.02, 0.03, 0.04),
    )
    front = dataclasses.replace(front_camera((120, 160)), crop=(100.0, 20.0, 640.0, 440.0), depth=True)
    spec = push_t_cell("fast")
    return dataclasses.replace(
        spec,
        name="rich",
        robot=RobotSpec(
            "builtin:xarm7_gripper",
            gaussians=scan.posed(q),
            gaussian_labels=scan.link_index,
            gaussian_links=tuple(model.link_names),
            gaussians_q=tuple(q),
            home_q=tuple(model.home_q),
            tool_contact=ContactSpec(0.0, 1.2),
            color_map=ColorMap(2, cmap),
        ),
        objects=(rope, block),
        colliders=(collider,),
        cameras=(front, wrist_camera("link7", (64, 96))),
        background_color_map=ColorMap(2, cmap),
        render_background=(0.1, 0.2, 0.3),
    )


def test_round_trip_is_lossless(tmp_path):
    for spec in (push_t_cell("fast"), rope_routing_cell("fast"), _rich_spec()):
        save_twin(spec, tmp_path / spec.name)
        assert_same(spec, load_twin(tmp_path / spec.name))
        # saving the loaded spec again writes the same twin.json
        save_twin(load_twin(tmp_path / spec.name), tmp_path / f"{spec.name}2")
        assert (tmp_path / spec.name / "twin.json").read_text() == (
            tmp_path / f"{spec.name}2" / "twin.json"
        ).read_text()


def test_rich_twin_builds_and_renders(tmp_path):
    spec = _rich_spec()
    save_twin(spec, tmp_path / "rich")
    twin, state = build_twin(load_twin(tmp_path / "rich"))
    assert twin.object_names == ["rope", "block"] and twin.model.num_particles == 67
    # the scanned robot Gaussians, taken into their link frames at q and posed again at q, come back
    q = np.asarray(spec.robot.gaussians_q)
    twin.reset(state, q)
    posed = twin.robot_gaussians.posed(q)
    mapped = spec.robot.color_map.apply(spec.robot.gaussians)
    order = np.argsort(spec.robot.gaussian_labels, kind="stable")
    np.testing.assert_allclose(posed.means, mapped.means[order], atol=2e-6)
    np.testing.assert_allclose(posed.base_colours, mapped.base_colours[order], atol=1e-6)
    frames = twin.render(state)
    assert frames["front"].rgb.shape == (120, 160, 3) and frames["wrist"].rgb.shape == (64, 96, 3)
    assert frames["front"].depth.max() > 0.3


def test_twin_export_takes_the_directory_as_path_or_out(tmp_path, capsys):
    from twinbench.cli import main

    assert main(["twin", "export", str(tmp_path / "a"), "--task", "point-reach"]) == 2  # no twin: refused
    assert "debug task" in capsys.readouterr().err
    assert main(["twin", "export", "--task", "push-t", "--preset", "fast", "--out", str(tmp_path / "b")]) == 0
    assert (tmp_path / "b" / "twin.json").is_file()
    assert main(["twin", "export", str(tmp_path / "c"), "--out", str(tmp_path / "d")]) == 2
    assert "once" in capsys.readouterr().err
    assert not (tmp_path / "c").exists() and not (tmp_path / "d").exists()


def test_builtin_and_exported_twins_give_bit_identical_episodes(tmp_path):
    assert export(ExportConfig(path=tmp_path / "pusht", preset="fast")) == 0
    actions = np.random.default_rng(0).uniform([0.35, -0.1], [0.55, 0.1], (12, 2)).astype(np.float32)
    runs = []
    for twin in (None, tmp_path / "pusht"):
        env = TwinEnv("push-t", preset="fast", twin=twin)
        obs, _ = env.reset(seed=4, options={"init_state": 6})
        trace = [obs["pixels"]["front"], obs["pixels"]["wrist"]]
        for a in actions:
            obs, reward, term, trunc, info = env.step(a)
            trace += [
                obs["pixels"]["front"],
                obs["pixels"]["wrist"],
                obs["agent_pos"],
                env.twin.particles(env.state, "tblock"),
                np.array([reward, info["is_success"], term, trunc]),
            ]
        runs.append(trace)
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(a, b)


def test_builtin_cells_write_the_geometry_their_tasks_read(tmp_path):
    save_twin(push_t_cell("fast"), tmp_path / "t")
    doc = json.loads((tmp_path / "t" / "twin.json").read_text())
    assert doc["version"] == 2 and doc["robot"]["tool_radius"] == 0.0102  # the study's 20 cm pusher
    assert doc["robot"]["urdf"] == "builtin:xarm7_pusher20"
    outline = doc["objects"][0]["outline"]
    assert len(outline["polygon"]) == 8 and outline["height"] == 0.03
    save_twin(rope_routing_cell("fast"), tmp_path / "r")
    doc = json.loads((tmp_path / "r" / "twin.json").read_text())
    assert doc["colliders"][0]["channel"] == [0.035, 0.03, 0.035] and doc["robot"]["tool_radius"] is None
    assert doc["robot"]["ee_link"] == "link7"  # the flange: the study's end-effector frame
    del doc["robot"]["ee_link"]  # a file written before (v1 or v2, no ee_link): the tool point, as then
    (tmp_path / "r" / "twin.json").write_text(json.dumps(doc))
    assert load_twin(tmp_path / "r").robot.ee_link is None
    assert load_spec_robot(load_twin(tmp_path / "r").robot).ee_link == "tcp"


def test_a_version_1_twin_without_geometry_still_loads(tmp_path):
    save_twin(push_t_cell("fast"), tmp_path / "t")
    path = tmp_path / "t" / "twin.json"
    doc = json.loads(path.read_text())
    doc["version"] = 1
    del doc["objects"][0]["outline"], doc["robot"]["tool_radius"]
    path.write_text(json.dumps(doc))
    spec = load_twin(tmp_path / "t")
    assert spec.objects[0].outline is None
    assert spec.robot.tool_radius == 0.0102  # the built-in pusher's rod, filled in
    with pytest.raises(ValueError, match="needs the outline of object 'tblock'"):
        TwinEnv("push-t", twin=tmp_path / "t")


def test_object_directory_round_trip(tmp_path):
    rope, block = _rich_spec().objects
    save_object(rope, tmp_path / "rope", sim={"drag_damping": 2.0, "collision_dist": 0.01})
    back, sim = load_object(tmp_path / "rope")
    assert_same(rope, back)
    save_object(block, tmp_path / "block")
    assert_same(block, load_object(tmp_path / "block")[0])
    assert sim == {"drag_damping": 2.0, "collision_dist": 0.01}
    with pytest.raises(ValueError, match="unknown SimParams"):
        save_object(rope, tmp_path / "x", sim={"drag": 1.0})


def test_task_in_a_twin_without_its_objects_names_what_is_missing(tmp_path):
    spec = push_t_cell("fast")
    block = dataclasses.replace(spec.objects[0], name="my_t")
    save_twin(dataclasses.replace(spec, objects=(block,)), tmp_path / "t")
    with pytest.raises(ValueError, match=r"needs object\(s\) \['tblock'\].*roles"):
        TwinEnv("push-t", twin=tmp_path / "t")
    env = TwinEnv("push-t", twin=tmp_path / "t", roles={"block": "my_t"})  # a role mapping fixes it
    _, info = env.reset(seed=0, options={"init_state": 1})
    assert info["status"] == "ok"
    with pytest.raises(ValueError, match="unknown setting"):
        TwinEnv("push-t", twin=tmp_path / "t", roles={"block": "my_t"}, pusher_friction=0.2)


# ---------------------------------------------------------------------------------------------- errors
@pytest.fixture(scope="module")
def good_dir(tmp_path_factory):
    root = tmp_path_factory.mktemp("twin")
    save_twin(_rich_spec(), root / "good")
    return root / "good"


def _broken(tmp_path, good_dir, edit=None, files=None):
    root = tmp_path / "broken"
    shutil.copytree(good_dir, root)
    doc = json.loads((root / "twin.json").read_text())
    if edit is not None:
        edit(doc)
    (root / "twin.json").write_text(json.dumps(doc))
    if files is not None:
        files(root)
    return root


def _set(path, value):
    def edit(doc):
        node = doc
        for k in path[:-1]:
            node = node[k]
        node[path[-1]] = value

    return edit


CASES = {
    "missing file": (
        dict(files=lambda r: (r / "objects" / "rope.npz").unlink()),
        r"objects\[0\]\(rope\)\.arrays: file 'objects/rope.npz' does not exist",
    ),
    "wrong shape": (
        dict(files=lambda r: np.savez(r / "objects" / "block.npz", particles=np.zeros((5, 2)))),
        r"objects\[1\]\(block\).*particles: expected a finite \(P, 3\) array",
    ),
    "explicit springs missing": (
        dict(files=lambda r: np.savez(r / "objects" / "rope.npz", particles=np.zeros((5, 3)))),
        r"objects\[0\]\(rope\)\.springs: 'explicit' needs a 'springs' \(M, 2\) array",
    ),
    "unknown field": (
        dict(edit=_set(["cameras", 0, "fov"], 60)),
        r"cameras\[0\]: unknown field\(s\) \['fov'\]",
    ),
    "pickle in npz": (
        dict(
            files=lambda r: np.savez(
                r / "objects" / "block.npz",
                particles=np.zeros((3, 3)),
                springs=np.array([{"a": 1}], dtype=object),
            )
        ),
        r"objects\[1\]\(block\)\.arrays: objects/block.npz holds pickled Python objects",
    ),
    "path escapes": (
        dict(edit=_set(["background", "gaussians"], "../../etc/passwd")),
        r"background\.gaussians: path '../../etc/passwd' leaves the directory",
    ),
    "absolute path": (
        dict(edit=_set(["objects", 1, "gaussians"], "/etc/passwd")),
        r"objects\[1\]\(block\)\.gaussians: path '/etc/passwd' is absolute",
    ),
    "bad pose": (
        dict(edit=_set(["objects", 0, "rest_pose"], [[1, 0, 0], [0, 1, 0]])),
        r"objects\[0\]\(rope\)\.rest_pose: expected a finite array of shape \(4, 4\)",
    ),
    "wrong version": (
        dict(edit=_set(["version"], 99)), r"version: this twinbench reads versions \[1, 2\], got 99"
    ),
    "clockwise outline": (
        dict(edit=_set(["objects", 1, "outline", "polygon"], [[0, 0.03], [0.02, -0.02], [-0.02, -0.02]])),
        r"objects\[1\]\(block\)\.outline: outline\.polygon: the vertices must go counter-clockwise",
    ),
    "outline not 2d": (
        dict(edit=_set(["objects", 1, "outline", "polygon"], [[0, 0, 0], [1, 0, 0], [0, 1, 0]])),
        r"objects\[1\]\(block\)\.outline\.polygon: expected a finite array of shape \(3, 2\)",
    ),
    "outline without height": (
        dict(edit=lambda d: d["objects"][1]["outline"].pop("height")),
        r"objects\[1\]\(block\)\.outline: missing field\(s\) \['height'\]",
    ),
    "bad channel": (
        dict(edit=_set(["colliders", 0, "channel"], [0.02, -0.03, 0.04])),
        r"colliders\[0\]\(box\): colliders\['box'\]\.channel: expected \(width, depth, length\) > 0",
    ),
    "bad tool radius": (
        dict(edit=_set(["robot", "tool_radius"], "wide")),
        r"robot\.tool_radius: expected a finite number, got 'wide'",
    ),
    "bad sim value": (
        dict(edit=_set(["sim", "dt"], -1.0)),
        r"twin\.json: sim\.dt: expected a number in \[1e-07, 0\.1\], got -1\.0$",
    ),
    "missing robot": (dict(edit=lambda d: d.pop("robot")), r"\(top level\): missing field\(s\) \['robot'\]"),
    "bad gaussians": (
        dict(files=lambda r: (r / "objects" / "block.ply").write_bytes(b"ply\nformat nonsense\n")),
        r"objects\[1\]\(block\)\.gaussians: .*block.ply",
    ),
    "bad colour map": (
        dict(edit=_set(["background", "color_map"], {"degree": 2, "coeffs": [[1, 2]]})),
        r"background\.color_map\.coeffs: colour map of degree 2 needs coefficients",
    ),
}


@pytest.mark.parametrize("case", list(CASES))
def test_malformed_twin_directories_give_one_line_errors(tmp_path, good_dir, case):
    kwargs, pattern = CASES[case]
    root = _broken(tmp_path, good_dir, **kwargs)
    with pytest.raises(TwinFormatError, match=pattern) as err:
        load_twin(root)
    message = str(err.value)
    assert "\n" not in message and str(root.resolve() / "twin.json") in message


def test_pickle_in_npz_is_never_unpickled(tmp_path, good_dir):
    marker = tmp_path / "executed"

    class Evil:
        def __reduce__(self):
            return (open, (str(marker), "w"))

    def plant(root):
        with open(root / "objects" / "block.npz", "wb") as f:
            np.savez(f, particles=np.zeros((3, 3)), springs=np.array([Evil()], dtype=object))

    root = _broken(tmp_path, good_dir, files=plant)
    with pytest.raises(TwinFormatError, match="pickled"):
        load_twin(root)
    assert not marker.exists()
    assert pickle  # the module the attack would rely on is the one np.load refuses to use


def test_not_a_twin_directory(tmp_path):
    with pytest.raises(TwinFormatError, match="not a directory"):
        load_twin(tmp_path / "nothing")
    (tmp_path / "empty").mkdir()
    with pytest.raises(TwinFormatError, match="twin.json"):
        load_twin(tmp_path / "empty")
    (tmp_path / "empty" / "twin.json").write_text("{not json")
    with pytest.raises(TwinFormatError, match="not valid JSON"):
        load_twin(tmp_path / "empty")


def test_physics_hash_ignores_appearance_only(tmp_path):
    """Twins that differ only in what rendering reads (name, cameras, Gaussians, colour maps) share a physics
    hash, read back from their folders too; any physical difference (an object's stiffness or mass, a
    collider's pose or contact, the robot's tool friction, the sim) gives another."""
    from twinbench.twin.files import twin_physics_hash

    spec = _rich_spec()
    rope, block = spec.objects
    box = spec.colliders[0]
    plain = dataclasses.replace(
        spec, name="other", cameras=spec.cameras[:1], background=_disc(10, (0.5, 0.5, 0.5)),
        background_color_map=None, render_background=(0.0, 0.0, 0.0),
        robot=dataclasses.replace(spec.robot, color_map=None, gaussians=None, gaussian_labels=None,
                                  gaussian_links=(), gaussians_q=None),
        objects=(dataclasses.replace(rope, color_map=None, gaussians=_disc(5, (1.0, 0.0, 0.0))), block),
        colliders=(dataclasses.replace(box, color_map=None, gaussians=None),))
    key = twin_physics_hash(spec)
    assert twin_physics_hash(plain) == key
    for name, s in (("a", spec), ("b", plain)):  # read back: the same (numbers typed as files give them)
        save_twin(s, tmp_path / name)
    assert twin_physics_hash(load_twin(tmp_path / "a")) == twin_physics_hash(load_twin(tmp_path / "b"))
    physical = [
        dataclasses.replace(spec, objects=(dataclasses.replace(rope, spring_Y=rope.spring_Y * 1.01), block)),
        dataclasses.replace(spec, objects=(rope, dataclasses.replace(block, mass=2.0))),
        dataclasses.replace(spec, colliders=(dataclasses.replace(box, pose=planar_pose(0.56, 0.2, 0.3)),)),
        dataclasses.replace(spec, colliders=(dataclasses.replace(box, contact=ContactSpec(0.1, 0.6)),)),
        dataclasses.replace(spec, robot=dataclasses.replace(spec.robot, tool_contact=ContactSpec(0.0, 1.0))),
        dataclasses.replace(spec, sim=dataclasses.replace(spec.sim, substeps=spec.sim.substeps + 1)),
        dataclasses.replace(spec, robot=dataclasses.replace(spec.robot, contact_mesh="convex_hull")),
    ]
    keys = {twin_physics_hash(s) for s in physical}
    assert len(keys) == len(physical) and key not in keys


def test_a_field_added_later_hashes_as_its_absence_at_its_default():
    """`hash_unless_default` fields (RobotSpec.contact_mesh) are left out of a twin's hash at their default,
    so twins built before the field existed (built-in cells, whose hash a resumed run checks) keep their
    hash; any other value counts."""
    import hashlib

    from twinbench.twin.files import _feed

    def digest(value) -> str:
        h = hashlib.sha256()
        _feed(h, value)
        return h.hexdigest()

    @dataclasses.dataclass
    class Part:  # as it was
        size: float

    before = digest(Part(1.0))

    @dataclasses.dataclass
    class Part:  # noqa: F811 - the same class with a field added later
        size: float
        shape: str = dataclasses.field(default="box", metadata={"hash_unless_default": True})

    assert digest(Part(1.0)) == before and digest(Part(1.0, "ball")) != before
    assert [f.name for f in dataclasses.fields(RobotSpec) if f.metadata.get("hash_unless_default")] == [
        "contact_mesh"]
