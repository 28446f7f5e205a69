"""Seeded fuzzing of every file format twinbench reads (issue 14): each mutated input either loads into
a valid result or raises the project's own error type, within a time and memory bound (fuzzlib).

Adding a format is one function returning a `Target` in FORMATS. TWINBENCH_FUZZ_CASES sets the number
of cases per format (default 150, ~10 s for all formats on 2 cores); `-m slow` runs 2000 per format."""

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
    def decode(data: bytes) -> bytes:
        with zipfile.ZipFile(io.BytesIO(data)) as zf:
            return zf.read(member)

    def encode(inner: bytes) -> bytes:
        src, out = zipfile.ZipFile(io.BytesIO(NPZ_SEED)), io.BytesIO()
        with zipfile.ZipFile(out, "w") as zf:
            for name in src.namelist():
                zf.writestr(name, inner if name == member else src.read(name))
        return out.getvalue()

    return decode, encode


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
    from twinbench.twin import (
        ColliderSpec,
        ObjectSpec,
        RobotSpec,
        TwinFormatError,
        TwinSpec,
        load_twin,
        save_twin,
    )
    from twinbench.twin.cells import front_camera

    pts = np.random.default_rng(0).uniform(-0.02, 0.02, (12, 3))
    springs = np.array([[i, (i + 1) % 12] for i in range(12)], np.int32)
    box = trimesh.creation.box(extents=(0.05, 0.05, 0.02))
    obj = ObjectSpec("obj", pts, springs=springs, spring_Y=np.full(12, 1e4), gaussians=_cloud())
    spec = TwinSpec("fuzz", RobotSpec("builtin:xarm7_pusher"), objects=(obj,),
                    colliders=(ColliderSpec("box", box.vertices, box.faces),), cameras=(front_camera(),),
                    background=_cloud(16, 0))
    root = tmp / "twin-seed"
    save_twin(spec, root)
    files = {p.relative_to(root).as_posix(): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}

    def check(loaded) -> None:
        assert isinstance(loaded, TwinSpec) and len(loaded.objects) == 1

    return Target(files, ".", load_twin, (TwinFormatError,), check,
                  mutable=("twin.json", "twin.json", "twin.json", "objects/obj.npz", "objects/obj.ply",
                           "colliders/box.obj", "background.ply"),
                  codecs={"objects/obj.npz": _npz_member_codec("springs.npy")})


FORMATS = [ply_binary, ply_ascii, splat, spz_v2, spz_v3, urdf, real_csv, replay_json, replay_npz,
           replay_npz_actions, lerobot_dataset, twin_dir]


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
