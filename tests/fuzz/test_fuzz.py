"""Seeded fuzzing of every file format twinbench reads (issue 14): each mutated input either loads into
a valid result or raises the project's own error type, within a time and memory bound (fuzzlib).

Adding a format is one function returning a `Target` in FORMATS (twin and object directories with every
array, PhysTwin pickles and .pth archives, calibration, boxes and build configs among them; a sample of
the twins that load is built and stepped). TWINBENCH_FUZZ_CASES sets the number of cases per format
(default 150); `-m slow` runs 2000 per format. Cases are bounded in CPU time, not wall time."""

from __future__ import annotations

import gzip
import io
import json
import os
import zipfile

import numpy as np
import pytest
import trimesh
from fuzzlib import Target, run_case

from twinbench.errors import InputError
from twinbench.gaussians.cloud import GaussianCloud
from twinbench.gaussians.io import LOG_SCALE_RANGE, GaussianFileError, load_gaussians, save_gaussians
from twinbench.robot.model import URDFError, load_robot

CASES = int(os.environ.get("TWINBENCH_FUZZ_CASES", "150"))
# mutated inputs legitimately trigger numpy overflow warnings and the readers' "ignoring ..." warnings
pytestmark = pytest.mark.filterwarnings("ignore::RuntimeWarning", "ignore::UserWarning")


# ---- valid seeds and checks --------------------------------------------------------------------------
def _cloud(n: int = 24, degree: int = 1) -> GaussianCloud:
    rng = np.random.default_rng(0)
    q = rng.normal(size=(n, 4))
    return GaussianCloud(rng.uniform(-1, 1, (n, 3)), q / np.linalg.norm(q, axis=1, keepdims=True),
                         rng.uniform(-5, -2, (n, 3)), rng.uniform(-2, 4, n),
                         rng.normal(scale=0.3, size=(n, (degree + 1) ** 2, 3)))


def _bytes_of(write, suffix: str, tmp) -> bytes:
    path = tmp / f"seed{suffix}"
    write(path)
    return path.read_bytes()


def _check_cloud(cloud) -> None:
    assert isinstance(cloud, GaussianCloud)
    for name in ("means", "quats", "log_scales", "logit_opacities", "sh"):
        assert np.all(np.isfinite(getattr(cloud, name))), name
    lo, hi = LOG_SCALE_RANGE
    assert np.all((cloud.log_scales >= lo) & (cloud.log_scales <= hi))
    assert np.all(np.linalg.norm(cloud.quats, axis=1) > 0)


def _gaussian_target(tmp, suffix, **save) -> Target:
    data = _bytes_of(lambda p: save_gaussians(_cloud(), p, **save), suffix, tmp)
    codecs = {f"seed{suffix}": (gzip.decompress, gzip.compress)} if suffix == ".spz" else {}
    return Target({f"seed{suffix}": data}, f"seed{suffix}", load_gaussians, (GaussianFileError,),
                  _check_cloud, codecs=codecs)


URDF = """<?xml version="1.0"?>
<robot name="fuzz">
  <material name="grey"><color rgba="0.5 0.5 0.5 1"/></material>
  <link name="base"><visual><geometry><box size="0.1 0.1 0.05"/></geometry>
    <material name="grey"/></visual></link>
  <link name="upper"><visual><origin xyz="0 0 0.1"/>
    <geometry><cylinder radius="0.02" length="0.2"/></geometry></visual></link>
  <link name="hand"><collision>
    <geometry><mesh filename="meshes/hand.stl" scale="1 1 1"/></geometry></collision></link>
  <link name="finger"><visual><geometry><sphere radius="0.01"/></geometry></visual></link>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0.05" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="elbow" type="continuous"><parent link="upper"/><child link="hand"/>
    <origin xyz="0 0 0.2" rpy="0 1.57 0"/><axis xyz="0 1 0"/></joint>
  <joint name="slide" type="prismatic"><parent link="hand"/><child link="finger"/>
    <origin xyz="0.05 0 0"/><axis xyz="1 0 0"/><limit lower="0" upper="0.04" effort="1" velocity="1"/></joint>
  <joint name="slide2" type="prismatic"><parent link="base"/><child link="mimic_finger"/>
    <axis xyz="0 1 0"/><limit lower="0" upper="0.04" effort="1" velocity="1"/>
    <mimic joint="slide" multiplier="-1" offset="0.04"/></joint>
  <link name="mimic_finger"/>
</robot>
"""


def _check_robot(model) -> None:
    assert np.all(model.lower <= model.upper)
    assert np.all(np.isfinite(model.fk(model.home_q)))


def _check_episodes(eps) -> None:
    assert eps
    for e in eps:
        assert isinstance(e.success, bool) and isinstance(e.init_state, int) and e.init_state >= 0
        assert e.actions.ndim == 2 and len(e.actions) >= 1 and np.all(np.isfinite(e.actions))
        assert isinstance(e.policy, str) and isinstance(e.checkpoint, str)


def _check_records(recs) -> None:
    assert recs
    for r in recs:
        assert isinstance(r.success, bool) and r.init_state >= 0 and abs(r.seed) < 2**63


def _npz_bytes(arrays: dict) -> bytes:
    buf = io.BytesIO()
    np.savez(buf, **arrays)
    return buf.getvalue()


def _npz_member_codec(member: str):
    """Mutate one .npy member inside the zip (re-zipped), not only the zip container."""
    return _zip_member_codec(NPZ_SEED, member)


_SEP = b"\n--npy member--\n"


def _npz_all_members_codec(seed: bytes):
    """Mutate the .npy members of an .npz as one text (so a mutation may hit any array), re-zipped under
    their names (a mutation that breaks a separator merges or drops members)."""
    with zipfile.ZipFile(io.BytesIO(seed)) as zf:
        names = zf.namelist()

    def decode(data: bytes) -> bytes:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            return _SEP.join(zf.read(n) for n in names)

    def encode(inner: bytes) -> bytes:
        out = io.BytesIO()
        with zipfile.ZipFile(out, "w") as zf:
            for name, part in zip(names, inner.split(_SEP), strict=False):
                zf.writestr(name, part)
        return out.getvalue()

    return decode, encode


def _folder_files(root) -> dict[str, bytes]:
    return {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _small_object():
    from twinbench.twin import ObjectSpec

    pts = np.random.default_rng(0).uniform(-0.02, 0.02, (12, 3))
    springs = np.array([[i, (i + 1) % 12] for i in range(12)], np.int32)
    return ObjectSpec("obj", pts, springs=springs, spring_Y=np.full(12, 1e4), gaussians=_cloud())


NPZ_SEED = _npz_bytes({"init_state": np.array([0, 3]), "success": np.array([True, False]),
                       "policy": np.array(["act", "act"]), "checkpoint": np.array(["s1", "s2"]),
                       "lengths": np.array([2, 3]), "actions": np.arange(10, dtype=np.float32).reshape(5, 2),
                       "seed": np.array([4, 5]), "train_step": np.array([-1, 100])})


# ---- formats: one function each ----------------------------------------------------------------------
def ply_binary(tmp) -> Target:
    return _gaussian_target(tmp, ".ply")


def ply_ascii(tmp) -> Target:
    return _gaussian_target(tmp, ".ply", ascii=True)


def splat(tmp) -> Target:
    return _gaussian_target(tmp, ".splat")


def spz_v2(tmp) -> Target:
    return _gaussian_target(tmp, ".spz", spz_version=2)


def spz_v3(tmp) -> Target:
    return _gaussian_target(tmp, ".spz", spz_version=3)


def urdf(tmp) -> Target:
    stl = io.BytesIO()
    trimesh.creation.box(extents=(0.02, 0.03, 0.04)).export(stl, file_type="stl")
    # a missing mesh is the loader's FileNotFoundError naming the link and the paths it tried
    return Target({"robot.urdf": URDF.encode(), "meshes/hand.stl": stl.getvalue()}, "robot.urdf",
                  load_robot, (URDFError, FileNotFoundError), _check_robot,
                  mutable=("robot.urdf", "robot.urdf", "robot.urdf", "meshes/hand.stl"))


def real_csv(tmp) -> Target:
    from twinbench.evaluation.real import read_real_csv

    text = ("policy,checkpoint,init_state,success,train_step,seed,task,notes\n"
            "act,step_1000,0,yes,1000,0,push-t,\nact,step_1000,1,no,1000,7,push-t,slipped\n"
            "expert,,2,TRUE,,,push-t,\n")  # one task on every row: import-real never assumes one
    return Target({"real.csv": text.encode()}, "real.csv", read_real_csv, (InputError,), _check_records)


def replay_json(tmp) -> Target:
    from twinbench.evaluation.replay import load_recorded

    log = {"episodes": [{"init_state": 1, "actions": [[0.1, 0.2], [0.0, -0.1]], "success": "false",
                         "policy": "act", "checkpoint": "s1", "seed": 3, "train_step": 10},
                        {"init_state": 2, "actions": [[0.0, 0.0]], "success": True, "policy": "act",
                         "checkpoint": "", "episode_index": 5}]}
    return Target({"log.json": json.dumps(log).encode()}, "log.json", load_recorded, (InputError,),
                  _check_episodes)


def replay_npz(tmp) -> Target:
    from twinbench.evaluation.replay import load_recorded

    codec = _npz_member_codec("lengths.npy")
    return Target({"log.npz": NPZ_SEED}, "log.npz", load_recorded, (InputError,), _check_episodes,
                  codecs={"log.npz": codec})


def replay_npz_actions(tmp) -> Target:
    from twinbench.evaluation.replay import load_recorded

    return Target({"log.npz": NPZ_SEED}, "log.npz", load_recorded, (InputError,), _check_episodes,
                  codecs={"log.npz": _npz_member_codec("actions.npy")})


def lerobot_dataset(tmp) -> Target:
    """A LeRobotDataset v3 folder: info.json, a data parquet file and an episodes parquet file."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from twinbench.evaluation.replay import load_recorded

    def parquet(table: dict) -> bytes:
        buf = io.BytesIO()
        pq.write_table(pa.table(table), buf)
        return buf.getvalue()

    info = {"codebase_version": "v3.0", "fps": 10, "features": {"action": {"dtype": "float32", "shape": [2]}}}
    data = parquet({"action": [[0.0, 0.1], [0.2, 0.3], [0.0, 0.0]], "episode_index": [0, 0, 1],
                    "frame_index": [0, 1, 0]})
    meta = parquet({"episode_index": [0, 1], "init_state": [0, 4], "success": ["no", "yes"],
                    "policy": ["act", "act"], "checkpoint": ["s1", "s1"]})
    files = {"meta/info.json": json.dumps(info).encode(), "data/chunk-000/file-000.parquet": data,
             "meta/episodes/chunk-000/file-000.parquet": meta}
    return Target(files, ".", load_recorded, (InputError,), _check_episodes, mutable=tuple(files))


def twin_dir(tmp) -> Target:
    """A small twin directory: twin.json, background and object Gaussians, object arrays with explicit
    springs and per-spring stiffness, a collider mesh."""
    from twinbench.errors import SimulationDiverged
    from twinbench.twin import (
        ColliderSpec,
        RobotSpec,
        TwinFormatError,
        TwinSpec,
        build_twin,
        load_twin,
        save_twin,
    )
    from twinbench.twin.cells import front_camera

    box = trimesh.creation.box(extents=(0.05, 0.05, 0.02))
    obj = _small_object()
    spec = TwinSpec("fuzz", RobotSpec("builtin:xarm7_pusher"), objects=(obj,),
                    colliders=(ColliderSpec("box", box.vertices, box.faces),), cameras=(front_camera(),),
                    background=_cloud(16, 0))
    root = tmp / "twin-seed"
    save_twin(spec, root)
    files = _folder_files(root)

    built = [0]

    def check(loaded) -> None:
        assert isinstance(loaded, TwinSpec) and len(loaded.objects) == 1
        built[0] += 1
        if built[0] <= 3 or built[0] % 10 == 0:  # build and step a sample of what loads (~0.6 s each)
            twin, state = build_twin(loaded)
            try:
                twin.step(state, twin.ee_state(state))  # hold the end effector where it is
            except SimulationDiverged:
                pass  # a valid twin may be unstable (its own stiffness and time step)

    return Target(files, ".", load_twin, (TwinFormatError,), check,
                  mutable=("twin.json", "twin.json", "twin.json", "objects/obj.npz", "objects/obj.ply",
                           "colliders/box.obj", "background.ply"),
                  codecs={"objects/obj.npz": _npz_all_members_codec(files["objects/obj.npz"])})


def object_dir(tmp) -> Target:
    """A standalone object directory (what mesh-to-object, import-phystwin and sysid write)."""
    from twinbench.twin import TwinFormatError, load_object, save_object

    root = tmp / "object-seed"
    save_object(_small_object(), root, sim={"drag_damping": 2.0, "ground_friction": 0.4, "substeps": 100})
    files = _folder_files(root)
    return Target(files, ".", load_object, (TwinFormatError,),
                  mutable=("object.json", "object.json", "obj.npz"),
                  codecs={"obj.npz": _npz_all_members_codec(files["obj.npz"])})


def sysid_dir(tmp) -> Target:
    """A sysid input folder (sysid.json + data.npz, what `twinbench sysid --data` reads); what loads is
    also checked by SysIdData's own validation (shapes, finite values, masks)."""
    from twinbench.construct.sysid_io import load_sysid_data, save_sysid_data
    from twinbench.construct.sysid_synthetic import synthetic_case
    from twinbench.physics.sysid_data import SysIdFormatError

    root = tmp / "sysid-seed"
    save_sysid_data(synthetic_case("rope", frames=4, validation_frames=1, seed=3)[0], root)
    files = _folder_files(root)

    def check(data) -> None:
        assert data.num_frames >= 1 and np.isfinite(data.particles).all()

    return Target(files, ".", load_sysid_data, (SysIdFormatError,), check,
                  mutable=("sysid.json", "data.npz", "data.npz"),
                  codecs={"data.npz": _npz_all_members_codec(files["data.npz"])})


PHYSTWIN_FINAL = {"object_points": np.zeros((3, 4, 3), np.float32),
                  "object_visibilities": np.ones((3, 4), bool),
                  "controller_points": np.zeros((3, 2, 3), np.float32), "surface_points": np.zeros((0, 3))}


def phystwin_pickle(tmp) -> Target:
    """final_data.pkl / optimal_params.pkl of a PhysTwin case (the restricted unpickler)."""
    import pickle

    from twinbench.construct.phystwin import PhysTwinFormatError, load_pickle

    data = pickle.dumps({**PHYSTWIN_FINAL, "params": {"drag_damping": np.float32(3.0), "n": 30, "s": "x"},
                         "shared": [PHYSTWIN_FINAL["object_points"]] * 3}, protocol=4)
    return Target({"final_data.pkl": data}, "final_data.pkl", load_pickle, (PhysTwinFormatError,))


def phystwin_pth(tmp) -> Target:
    """best_EPOCH.pth (torch's zip layout, read without torch): the archive and its data.pkl."""
    from twinbench.construct.phystwin import PhysTwinFormatError, load_torch_zip, save_torch_zip

    save_torch_zip({"spring_Y": np.arange(1, 41, dtype=np.float32),
                    "collide_elas": np.array([0.5], np.float32),
                    "num_object_springs": 30, "strided": np.arange(12.0).reshape(3, 4)[:, ::2]},
                   tmp / "best_1.pth")
    data = (tmp / "best_1.pth").read_bytes()
    return Target({"best_1.pth": data}, "best_1.pth", load_torch_zip, (PhysTwinFormatError,),
                  codecs={"best_1.pth": _zip_member_codec(data, "best_1/data.pkl")})


def _zip_member_codec(seed: bytes, member: str):
    """Mutate one member of a zip archive (`seed`), re-zipping the others unchanged."""
    def decode(data: bytes) -> bytes:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            return zf.read(member)

    def encode(inner: bytes) -> bytes:
        src, out = zipfile.ZipFile(io.BytesIO(seed)), io.BytesIO()
        with zipfile.ZipFile(out, "w") as zf:
            for name in src.namelist():
                zf.writestr(name, inner if name == member else src.read(name))
        return out.getvalue()

    return decode, encode


CALIBRATION = {"base_to_world": np.eye(4).tolist(), "cameras": [
    {"name": "front", "intrinsics": [300.0, 300.0, 160.0, 120.0], "sensor_size": [320, 240],
     "camera_to_world": [[1, 0, 0, 0.1], [0, -1, 0, 0.0], [0, 0, -1, 1.0], [0, 0, 0, 1]],
     "crop": [0, 0, 320, 240], "output_hw": [120, 160]},
    {"name": "wrist", "K": [[200, 0, 80], [0, 200, 60], [0, 0, 1]], "sensor_size": [160, 120],
     "hand_eye": np.eye(4).tolist(), "mount_link": "link7", "axes": "opengl", "depth": True}]}


def calibration(tmp) -> Target:
    from twinbench.construct.calibration import load_calibration

    def check(cams) -> None:
        assert len(cams) >= 1 and all(np.all(np.isfinite(c.pose)) for c in cams)

    return Target({"calibration.json": json.dumps(CALIBRATION).encode()}, "calibration.json",
                  load_calibration, (ValueError,), check)


BOXES = {"transform": np.eye(4).tolist(), "robot": [{"center": [0, 0, 0.3], "half_extents": [0.1, 0.1, 0.3]}],
         "objects": {"block": {"center": [0.4, 0, 0.02], "half_extents": [0.05, 0.05, 0.02],
                               "rpy_deg": [0, 0, 10]}},
         "bounds": {"center": [0.3, 0, 0], "half_extents": [0.7, 0.7, 1.0]}}


def boxes(tmp) -> Target:
    from twinbench.construct.segment import load_boxes

    return Target({"boxes.json": json.dumps(BOXES).encode()}, "boxes.json", load_boxes, (ValueError,))


def build_config(tmp) -> Target:
    """A `twin build` config with the object folder, calibration and collider mesh it names."""
    from twinbench.construct.build_config import build_spec_from_config
    from twinbench.twin import TwinSpec, save_object

    root = tmp / "build-seed"
    save_object(_small_object(), root / "objects" / "obj", sim={"substeps": 100})
    (root / "calibration.json").write_text(json.dumps({"cameras": CALIBRATION["cameras"][:1]}))
    trimesh.creation.box(extents=(0.05, 0.05, 0.02)).export(root / "box.obj")
    (root / "color.json").write_text(json.dumps({"degree": 1, "coeffs": np.eye(3, 4).tolist()}))
    config = {"name": "cell", "robot": {"urdf": "builtin:xarm7_pusher", "color_map": "color.json"},
              "objects": [{"dir": "objects/obj", "name": "block", "rest_pose": np.eye(4).tolist()}],
              "colliders": [{"name": "box", "mesh": "box.obj", "pose": np.eye(4).tolist(), "friction": 0.4}],
              "cameras": "calibration.json", "sim": {"ground_friction": 0.5},
              "controller": {"control_hz": 30.0},
              "render": {"background": [0.1, 0.2, 0.3]}}
    (root / "build.json").write_text(json.dumps(config))
    files = _folder_files(root)

    def check(spec) -> None:
        assert isinstance(spec, TwinSpec) and len(spec.objects) == 1

    return Target(files, "build.json", build_spec_from_config, (ValueError, FileNotFoundError), check,
                  mutable=("build.json", "build.json", "build.json", "color.json", "box.obj"))


FORMATS = [ply_binary, ply_ascii, splat, spz_v2, spz_v3, urdf, real_csv, replay_json, replay_npz,
           replay_npz_actions, lerobot_dataset, twin_dir, object_dir, sysid_dir, phystwin_pickle,
           phystwin_pth, calibration, boxes, build_config]


@pytest.fixture(scope="module")
def workdir(tmp_path_factory):
    return tmp_path_factory.mktemp("fuzz")


def _run(fmt, workdir, n: int) -> dict[str, int]:
    target = fmt(workdir)
    counts = {"loaded": 0, "refused": 0}
    for i in range(n):
        counts[run_case(target, fmt.__name__, i, workdir)] += 1
    return counts


@pytest.mark.parametrize("fmt", FORMATS, ids=lambda f: f.__name__)
def test_fuzz(fmt, workdir):
    counts = _run(fmt, workdir, CASES)
    assert counts["refused"] > 0  # the mutations do reach the validation


@pytest.mark.parametrize("fmt", FORMATS, ids=lambda f: f.__name__)
def test_seeds_are_valid(fmt, workdir):
    target = fmt(workdir)
    root = workdir / f"seed-{fmt.__name__}"
    for rel, data in target.files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data)
    target.check(target.load(root / target.entry))


@pytest.mark.slow
@pytest.mark.parametrize("fmt", FORMATS, ids=lambda f: f.__name__)
def test_fuzz_long(fmt, workdir):
    _run(fmt, workdir, 2000)
