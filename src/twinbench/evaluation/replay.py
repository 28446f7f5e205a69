"""Open-loop replay of recorded real rollouts in the twin, and replay-vs-real confusion matrices.

Each recorded episode's commanded actions are replayed from its initial state; the replay outcome is
stored with domain "replay" next to the recorded real outcome (domain "real"), both under the same
run id and key (policy, checkpoint, init_state, seed), where seed = the recorded episode's `seed`
field if given, else its episode index (so episodes from the same initial state stay distinct).
A replay stops when the actions run out or the twin's episode ends (termination / time limit).

Sources (`load_recorded`):
- a LeRobotDataset v3 folder: `meta/info.json` (codebase_version "v3.x", feature "action"),
  `data/chunk-XXX/file-XXX.parquet` (columns `action`, `episode_index`, `frame_index`) and
  `meta/episodes/chunk-XXX/file-XXX.parquet` with per-episode columns `episode_index` plus the
  twinbench outcome columns `init_state`, `success`, `policy`, `checkpoint` (optional `train_step`,
  `seed`); the outcome columns may instead come from an `outcomes` JSON file (schema as below,
  without `actions`, keyed by `episode_index`);
- a JSON log: `{"episodes": [{"init_state": int, "actions": [[...], ...] (T x A), "success": bool,
  "policy": str, "checkpoint": str, optional "seed", "train_step", "episode_index", "object_poses"}]}`,
  where a robot log may stand in for "actions": "ee_poses" (T x 7: x, y, z, qw, qx, qy, qz of the twin's
  end-effector frame in the robot base frame, per frame) or "joint_positions" (T x n_arm_joints, rad),
  each with an optional "gripper" (T,) for the gripper tasks; they become the task's absolute actions
  (planar tasks: the pose's x, y; gripper tasks: the pose and the gripper value);
  "object_poses" = {role or object: [x, y, theta]}: the measured start poses of the objects (world, m and
  rad), which replace the grid state's (the env's `object_poses` reset option);
- an NPZ log (read with allow_pickle=False): `init_state (E,)`, `success (E,)`, `policy (E,) str`,
  `checkpoint (E,) str`, `lengths (E,)`, `actions (sum T, A)` (episodes concatenated in order),
  optional `seed (E,)`, `train_step (E,)` (-1 = none).
"""

from __future__ import annotations

import json
from collections.abc import Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from twinbench.errors import InputError
from twinbench.evaluation.store import (
    DEFAULT_DB,
    EpisodeRecord,
    ResultsStore,
    check_run_id,
    parse_int,
    parse_success,
)

_OUTCOME_FIELDS = ("init_state", "success", "policy", "checkpoint")


@dataclass(frozen=True)
class RecordedEpisode:
    """One real rollout: where it started, what was commanded, how it ended."""

    episode_index: int
    init_state: int
    actions: np.ndarray  # (T, A)
    success: bool
    policy: str
    checkpoint: str = ""
    train_step: int | None = None
    seed: int | None = None
    object_poses: dict | None = None  # {role or object: (x, y, theta)} measured at the start
    robot_log: tuple[str, np.ndarray, np.ndarray | None] | None = None  # (kind, (T, D), gripper (T,))
    study_index: int | None = None  # the recording's own init_state when an index map translated it

    @property
    def key_seed(self) -> int:
        return self.episode_index if self.seed is None else int(self.seed)


MAX_LOG_BYTES = 2 * 2**30
"""Largest JSON / NPZ log (uncompressed NPZ members) read; larger ones are refused before parsing."""


def _field(where: str, index: int, name: str, parse, value):
    try:
        return parse(value)
    except InputError as err:
        raise InputError(f"{where}: episode {index} field {name!r}: {err}") from None


def _text(value) -> str:
    if isinstance(value, bytes):
        return value.decode("utf-8", "replace")
    if value is None or not isinstance(value, str | np.str_):
        raise InputError(f"{value!r} is not a string")
    return str(value)


def _optional_int(value, minimum: int | None = None) -> int | None:
    """None (or -1 for train_step, the NPZ convention for 'none') -> None; else a strict int."""
    return None if value is None else parse_int(value, minimum=minimum)


def _episode_from_dict(d: dict, where: str, index: int, actions=None) -> RecordedEpisode:
    if not isinstance(d, dict):
        raise InputError(f"{where}: episode {index} is a {type(d).__name__}, expected an object with fields "
                         "init_state, actions (T x A), success, policy, checkpoint")
    log_kind = next((k for k in ("ee_poses", "joint_positions") if k in d), None) if actions is None else None
    needs = () if actions is not None or log_kind else ("actions",)
    missing = [f for f in _OUTCOME_FIELDS + needs if f not in d]
    if missing:
        raise InputError(f"{where}: episode {index} lacks field(s) {missing}; each episode needs "
                         f"init_state, actions (T x A) or a robot log (ee_poses / joint_positions), success, "
                         "policy, checkpoint")
    robot_log = None
    if log_kind and "actions" not in d:
        log = _finite_2d(d[log_kind], where, index, log_kind)
        if log_kind == "ee_poses" and log.shape[1] != 7:
            raise InputError(f"{where}: episode {index} field 'ee_poses' must be (T, 7) (x, y, z, qw, qx, "
                             f"qy, qz), got shape {log.shape}")
        grip = None
        if d.get("gripper") is not None:
            grip = _finite_2d(np.reshape(np.asarray(d["gripper"], dtype=object), (-1, 1)), where, index,
                              "gripper")[:, 0]
            if len(grip) != len(log):
                raise InputError(f"{where}: episode {index} field 'gripper' has {len(grip)} values for "
                                 f"{len(log)} frames")
        robot_log = (log_kind, log, grip)
        actions = np.zeros((len(log), 0))  # placeholder: the actions come from the log in the twin
    poses = d.get("object_poses")
    if poses is not None and not isinstance(poses, dict):
        raise InputError(f"{where}: episode {index} field 'object_poses' must be an object "
                         "{role or object: [x, y, theta]}")
    try:
        acts = np.asarray(d["actions"] if actions is None else actions, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as err:
        raise InputError(f"{where}: episode {index} field 'actions' is not a numeric (T, A) array "
                         f"({err})") from None
    if robot_log is None and (acts.ndim != 2 or len(acts) == 0 or not np.all(np.isfinite(acts))):
        raise InputError(f"{where}: episode {index} field 'actions' must be a finite (T, A) array with "
                         f"T >= 1, got shape {acts.shape}")
    step = d.get("train_step")
    if step is not None and not isinstance(step, bool | np.bool_) and np.ndim(step) == 0:
        try:
            step = None if float(step) == -1 else step  # NPZ: -1 = no train step
        except (TypeError, ValueError):
            pass
    checkpoint = d["checkpoint"]
    return RecordedEpisode(
        episode_index=_field(where, index, "episode_index", lambda v: parse_int(v, minimum=0),
                             d.get("episode_index", index)),
        init_state=_field(where, index, "init_state", lambda v: parse_int(v, minimum=0), d["init_state"]),
        actions=acts,
        success=_field(where, index, "success", parse_success, d["success"]),
        policy=_field(where, index, "policy", _text, d["policy"]),
        checkpoint="" if checkpoint is None else _field(where, index, "checkpoint", _text, checkpoint),
        train_step=_field(where, index, "train_step", lambda v: _optional_int(v, 0), step),
        seed=_field(where, index, "seed", _optional_int, d.get("seed")),
        object_poses=None if poses is None else {str(k): v for k, v in poses.items()},
        robot_log=robot_log,
    )


def _finite_2d(value, where: str, index: int, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as err:
        raise InputError(f"{where}: episode {index} field {name!r} is not numeric ({err})") from None
    if arr.ndim != 2 or len(arr) == 0 or not np.all(np.isfinite(arr)):
        raise InputError(f"{where}: episode {index} field {name!r} must be a finite (T, D) array with "
                         f"T >= 1, got shape {arr.shape}")
    return arr


def log_actions(env, ep: RecordedEpisode) -> np.ndarray:
    """The task's absolute actions (T, A) of a robot log: end-effector poses as they are, or joint
    positions through the twin's forward kinematics (its end-effector frame); planar tasks take x, y,
    gripper tasks the pose and the gripper value (open when the log has none)."""
    kind, log, grip = ep.robot_log
    twin = env.unwrapped.twin
    shape = env.action_space.shape
    if kind == "joint_positions":
        robot = twin.robot
        n = len(robot.arm_joints)
        if log.shape[1] != n:
            raise InputError(f"episode {ep.episode_index}: joint_positions has {log.shape[1]} columns, the "
                             f"twin's arm has {n} joints")
        from twinbench.transforms import matrix_to_quat

        q = np.tile(robot.home_q, (len(log), 1))
        q[:, robot.arm_q_indices] = log
        poses = robot.ee_pose(q)
        log = np.concatenate([poses[:, :3, 3], matrix_to_quat(poses[:, :3, :3])], axis=1)
    if shape == (2,):
        return log[:, :2].copy()
    if shape == (8,):
        g = np.full(len(log), float(env.action_space.low[7])) if grip is None else grip
        return np.concatenate([log[:, :7], g[:, None]], axis=1)
    raise InputError(f"episode {ep.episode_index}: a robot log ({kind}) becomes actions of shape (2,) or "
                     f"(8,); this task's are {shape}: give 'actions' instead")


def _read_json(path: Path):
    """Parse a JSON file (size-bounded); InputError naming the file on any problem."""
    try:
        size = path.stat().st_size
        if size > MAX_LOG_BYTES:
            raise InputError(f"{path}: {size} bytes, over the {MAX_LOG_BYTES}-byte limit for a JSON log; "
                             "split it or use an NPZ log")
        return json.loads(path.read_bytes())
    except (UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"{path}: not valid JSON ({err}); fix or re-export the file") from None
    except RecursionError:
        raise InputError(f"{path}: JSON nested too deeply; fix or re-export the file") from None


def load_json_log(path: str | Path) -> list[RecordedEpisode]:
    path = Path(path)
    data = _read_json(path)
    eps = data.get("episodes") if isinstance(data, dict) else data
    if not isinstance(eps, list) or not eps:
        raise InputError(f"{path}: expected {{'episodes': [...]}} with at least one episode")
    return [_episode_from_dict(d, str(path), i) for i, d in enumerate(eps)]


def _load_npz(path: Path) -> dict[str, np.ndarray]:
    """The arrays of an .npz (no pickles), every member's size checked before it is inflated/allocated."""
    import io
    import zipfile

    out, total = {}, 0
    try:
        with zipfile.ZipFile(path) as zf:
            for info in zf.infolist():
                total += info.file_size
                if total > MAX_LOG_BYTES:
                    raise InputError(f"{path}: members inflate to more than {MAX_LOG_BYTES} bytes (limit)")
                with zf.open(info) as fh:
                    raw = fh.read(info.file_size + 1)  # never more than the declared size (+1 to see excess)
                if len(raw) != info.file_size:
                    raise InputError(f"{path}: member {info.filename!r} does not match its declared size")
                buf = io.BytesIO(raw)
                version = np.lib.format.read_magic(buf)
                read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                               (2, 0): np.lib.format.read_array_header_2_0}.get(version)
                if read_header is None:
                    raise InputError(f"{path}: member {info.filename!r} uses .npy format {version}; "
                                     "save with numpy.savez")
                shape, _, dtype = read_header(buf)
                if dtype.hasobject:
                    raise InputError(f"{path}: member {info.filename!r} holds Python objects (pickles are "
                                     "never loaded); store plain numeric / string arrays")
                if int(np.prod(shape, dtype=object)) * dtype.itemsize > len(raw):
                    raise InputError(f"{path}: member {info.filename!r} declares shape {shape}, larger "
                                     "than its data")
                buf.seek(0)
                out[info.filename.removesuffix(".npy")] = np.lib.format.read_array(buf, allow_pickle=False)
    except InputError:
        raise
    except Exception as err:  # noqa: BLE001 - zipfile and numpy's header parser (tokenize, ast) raise many types
        raise InputError(f"{path}: not a valid .npz file ({type(err).__name__}: {err})") from None
    return out


def load_npz_log(path: str | Path) -> list[RecordedEpisode]:
    path = Path(path)
    arrays = _load_npz(path)
    missing = [k for k in ("init_state", "success", "policy", "checkpoint", "lengths", "actions")
               if k not in arrays]
    if missing:
        raise InputError(f"{path}: missing array(s) {missing} (see twinbench.evaluation.replay)")
    lengths = arrays["lengths"]
    if lengths.ndim != 1 or lengths.dtype.kind not in "iu" or np.any(lengths < 1):
        raise InputError(f"{path}: 'lengths' must be a 1-D integer array of episode lengths >= 1")
    n = len(lengths)
    for k in ("init_state", "success", "policy", "checkpoint", "seed", "train_step"):
        if k in arrays and (arrays[k].ndim != 1 or len(arrays[k]) != n):
            raise InputError(f"{path}: {k!r} must be a 1-D array of {n} values (one per episode), got shape "
                             f"{arrays[k].shape}")
    total = int(np.sum(lengths, dtype=object))
    if arrays["actions"].ndim != 2 or total != len(arrays["actions"]):
        raise InputError(f"{path}: sum(lengths) = {total} != len(actions) = {len(arrays['actions'])} "
                         "(actions must be (sum T, A))")
    starts = np.concatenate([[0], np.cumsum(lengths)])
    out = []
    for i in range(n):
        d = {k: arrays[k][i] for k in ("init_state", "success", "policy", "checkpoint", "seed", "train_step")
             if k in arrays}
        out.append(_episode_from_dict(d, str(path), i, arrays["actions"][starts[i]:starts[i + 1]]))
    return out


def _read_parquet(path: Path, columns: list[str] | None = None):
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError as err:  # e.g. pyarrow >= 26 beside numpy 1.x (its metadata does not require numpy 2)
        raise ImportError(f"reading {path} needs pyarrow, which failed to import ({err}); with numpy 1.x "
                          "(e.g. beside openpi) install pyarrow < 26: pip install 'pyarrow>=18,<26'") from err

    try:
        return pq.read_table(path, columns=columns).to_pylist()
    except (pa.ArrowException, OSError, ValueError, KeyError) as err:
        raise InputError(f"{path}: cannot read this parquet file ({type(err).__name__}: {err}); "
                         "re-export the dataset") from None


def load_lerobot_dataset(folder: str | Path, outcomes: str | Path | None = None) -> list[RecordedEpisode]:
    """Recorded episodes of a LeRobotDataset v3 folder (actions from data/, outcomes from meta/episodes/)."""
    folder = Path(folder)
    info_path = folder / "meta" / "info.json"
    if not info_path.is_file():
        raise InputError(f"{folder}: no meta/info.json; not a LeRobotDataset folder")
    info = _read_json(info_path)
    if not isinstance(info, dict):
        raise InputError(f"{info_path}: expected a JSON object with codebase_version and features")
    version = str(info.get("codebase_version", ""))
    if not version.startswith("v3"):
        raise InputError(f"{info_path}: codebase_version {version!r} is not v3.x; convert the dataset to v3 "
                         "(lerobot's convert_dataset_v21_to_v30) first")
    features = info.get("features", {})
    if not isinstance(features, dict) or "action" not in features:
        raise InputError(f"{info_path}: features has no 'action'")
    data_files = sorted((folder / "data").glob("chunk-*/file-*.parquet"))
    if not data_files:
        raise InputError(f"{folder}: no data/chunk-XXX/file-XXX.parquet files")
    actions: dict[int, list[tuple[int, np.ndarray]]] = {}
    for f in data_files:
        for i, row in enumerate(_read_parquet(f, ["episode_index", "frame_index", "action"])):
            ep = _field(str(f), i, "episode_index", lambda v: parse_int(v, minimum=0), row["episode_index"])
            fr = _field(str(f), i, "frame_index", lambda v: parse_int(v, minimum=0), row["frame_index"])
            try:
                act = np.asarray(row["action"], dtype=np.float64)
            except (TypeError, ValueError) as err:
                raise InputError(f"{f}: row {i} 'action' is not numeric ({err})") from None
            actions.setdefault(ep, []).append((fr, act))
    meta_rows: dict[int, dict] = {}
    for f in sorted((folder / "meta" / "episodes").glob("chunk-*/file-*.parquet")):
        for i, row in enumerate(_read_parquet(f)):
            if "episode_index" not in row:
                raise InputError(f"{f}: no 'episode_index' column")
            meta_rows[_field(str(f), i, "episode_index", parse_int, row["episode_index"])] = row
    if outcomes is not None:
        outcomes = Path(outcomes)
        if not outcomes.is_file():
            raise InputError(f"outcomes file {outcomes} does not exist")
        extra = _read_json(outcomes)
        entries = extra.get("episodes", extra) if isinstance(extra, dict) else extra
        if not isinstance(entries, list):
            raise InputError(f"{outcomes}: expected {{'episodes': [...]}} or a list of per-episode objects")
        for i, d in enumerate(entries):
            if not isinstance(d, dict) or "episode_index" not in d:
                raise InputError(f"{outcomes}: entry {i} lacks 'episode_index'")
            meta_rows.setdefault(_field(str(outcomes), i, "episode_index", parse_int, d["episode_index"]),
                                 {}).update(d)
    out = []
    for ep in sorted(actions):
        frames = sorted(actions[ep], key=lambda x: x[0])
        if [f for f, _ in frames] != list(range(len(frames))):
            raise InputError(f"{folder}: episode {ep} has non-contiguous frame_index values")
        if len({a.shape for _, a in frames}) != 1:
            raise InputError(f"{folder}: episode {ep} has actions of different lengths")
        row = dict(meta_rows.get(ep, {}))
        row["episode_index"] = ep
        where = f"{folder} (meta/episodes or outcomes file)"
        out.append(_episode_from_dict(row, where, ep, np.stack([a for _, a in frames])))
    return out


def load_recorded(source: str | Path, outcomes: str | Path | None = None) -> list[RecordedEpisode]:
    """Dispatch on the source: LeRobotDataset v3 folder, .json log or .npz log."""
    source = Path(source)
    if source.is_dir():
        return load_lerobot_dataset(source, outcomes)
    if not source.is_file():
        raise InputError(f"replay source {source} does not exist")
    if source.suffix == ".json":
        return load_json_log(source)
    if source.suffix == ".npz":
        return load_npz_log(source)
    raise InputError(f"replay source {source}: expected a LeRobotDataset folder, a .json or an .npz log")


def replay_episodes(task: str, episodes: list[RecordedEpisode], store: ResultsStore | str | Path = DEFAULT_DB,
                    run_id: str = "replay", *, env_kwargs: dict | None = None,
                    index_map: str | Path | None = None,
                    workers: int = 0) -> list[tuple[EpisodeRecord, EpisodeRecord]]:
    """Replay each recorded episode in `task`'s twin; store and return (real, replay) record pairs, in the
    episodes' order. `index_map`: a CSV/JSON map from the recording's init_state values to the task's grid
    indices (`grids.read_index_map`); an episode with `object_poses` starts from them instead of the grid
    state's. `workers` >= 1 replays in that many worker processes (as `evaluate` runs episodes; each
    episode's actions go to them as an `actions:FILE.npy` policy), 0 in this process. Episodes whose
    replay run `run_id` already holds (status ok) are not replayed again: an interrupted replay resumes."""
    import tempfile
    import time

    from twinbench.evaluation.backends import refuse_in_worker_import, run_local
    from twinbench.evaluation.grids import grid_info, map_index, read_index_map
    from twinbench.evaluation.rollout import EpisodeBatch, EpisodeJob, run_episode
    from twinbench.evaluation.runner import (
        _check_counts,
        _twin_hash,
        add_run_seconds_quietly,
        moved_twin_keys,
    )
    from twinbench.policies.base import OpenLoopPolicy
    from twinbench.tasks import get_task

    refuse_in_worker_import("replay_episodes")
    check_run_id(run_id)
    _check_counts(workers, 0)
    spec = get_task(task)
    if index_map is not None:
        mapping = read_index_map(index_map, spec.n_grid_states)
        episodes = [replace(ep, init_state=map_index(mapping, ep.init_state, f"episode {ep.episode_index}"),
                            study_index=ep.init_state) for ep in episodes]
    for ep in episodes:  # a replay starts from the recorded grid state, never from a sampled one
        if not 0 <= ep.init_state < spec.n_grid_states:
            raise InputError(f"episode {ep.episode_index}: init_state {ep.init_state} is not a grid state "
                             f"of task {task!r} (0..{spec.n_grid_states - 1}); the env would sample a "
                             "random state instead of replaying the recorded one. Fix the recording")
    store = store if isinstance(store, ResultsStore) else ResultsStore(store)
    env = spec.make_env(**(env_kwargs or {}))
    a_shape = env.action_space.shape
    episodes = [replace(ep, actions=log_actions(env, ep)) if ep.robot_log is not None else ep
                for ep in episodes]
    for ep in episodes:
        if ep.actions.shape[1:] != a_shape:
            raise InputError(f"episode {ep.episode_index}: actions of shape {ep.actions.shape[1:]} per step, "
                             f"task {task!r} expects {a_shape}")
    if workers:
        env.close()  # the workers build their own
    protocol = {"task": task, "kind": "replay", "n_episodes": len(episodes),
                "env_kwargs": dict(env_kwargs or {}), "grid": grid_info(task, env_kwargs),
                "index_map": None if index_map is None else str(index_map)}
    if spec.task_cls is not None:  # resuming must replay in the same twin
        protocol["twin_hash"] = _twin_hash(task, dict(env_kwargs or {}), run_id, store)
    # more recorded episodes extend the run; a moved twin keeps it
    store.start_run(run_id, task, protocol, grow=("n_episodes", *moved_twin_keys(store, run_id, protocol)))

    def key(ep: RecordedEpisode) -> tuple:
        return ep.policy, ep.checkpoint, ep.init_state, ep.key_seed

    def pair(ep: RecordedEpisode, success: bool, status: str, steps: int, wall_time_s: float | None,
             metrics: dict) -> tuple[EpisodeRecord, EpisodeRecord]:
        extra = {"episode_index": ep.episode_index}
        if ep.study_index is not None:
            extra["study_index"] = ep.study_index
        if ep.object_poses is not None:
            extra["object_poses"] = ep.object_poses
        common = dict(run_id=run_id, task=task, policy=ep.policy, checkpoint=ep.checkpoint,
                      train_step=ep.train_step, init_state=ep.init_state, seed=ep.key_seed)
        real = EpisodeRecord(**common, domain="real", success=ep.success, status="ok",
                             steps=len(ep.actions), metrics=extra)
        rep = EpisodeRecord(**common, domain="replay", success=success, status=status, steps=steps,
                            wall_time_s=wall_time_s, metrics={**metrics, **extra})
        if status == "sim_error" and "object_poses" in str(metrics.get("error", "")):
            raise InputError(f"episode {ep.episode_index}: {str(metrics['error']).removeprefix('reset: ')}")
        store.record_episodes([real, rep])
        return real, rep

    def stored(domain: str) -> dict:
        recs = store.episodes(run_id, domain=domain)
        return {(r.policy, r.checkpoint, r.init_state, r.seed): r for r in recs}

    done, real_done = stored("replay"), stored("real")
    pairs = {key(ep): (real_done[key(ep)], done[key(ep)]) for ep in episodes
             if key(ep) in real_done and key(ep) in done and done[key(ep)].status == "ok"}
    todo = [ep for ep in episodes if key(ep) not in pairs]
    t0 = time.perf_counter()
    try:
        if not workers:
            for ep in todo:
                options = None if ep.object_poses is None else {"object_poses": ep.object_poses}
                out = run_episode(env, OpenLoopPolicy(ep.actions), init_state=ep.init_state,
                                  seed=ep.key_seed, max_steps=len(ep.actions), reset_options=options)
                pairs[key(ep)] = pair(ep, out.success, out.status, out.steps, out.wall_time_s,
                                      out.metrics())
        elif todo:
            with tempfile.TemporaryDirectory(prefix="twinbench-replay-") as tmp:
                by_file, batches = {}, []
                for i, ep in enumerate(todo):
                    path = Path(tmp) / f"ep{i}.npy"
                    np.save(path, np.asarray(ep.actions), allow_pickle=False)
                    by_file[path.stem] = ep
                    options = None if ep.object_poses is None else {"object_poses": ep.object_poses}
                    batches.append(EpisodeBatch((EpisodeJob(
                        task, f"actions:{path}", ep.init_state, ep.key_seed, run_id,
                        dict(env_kwargs or {}), max_steps=len(ep.actions), reset_options=options),)))

                def on_done(rec: EpisodeRecord) -> None:
                    ep = by_file[rec.checkpoint]
                    pairs[key(ep)] = pair(ep, rec.success, rec.status, rec.steps, rec.wall_time_s,
                                          rec.metrics)

                run_local(batches, int(workers), on_done)
    finally:
        if todo:
            add_run_seconds_quietly(store, run_id, time.perf_counter() - t0)
    return [pairs[key(ep)] for ep in episodes]


@dataclass(frozen=True)
class Confusion:
    """Replay outcome (prediction) vs real outcome (truth); positive = success."""

    tp: int = 0  # replay success, real success
    fp: int = 0  # replay success, real failure
    fn: int = 0  # replay failure, real success
    tn: int = 0  # replay failure, real failure
    excluded: int = 0  # pairs whose replay ended in an error (not counted above)

    @property
    def n(self) -> int:
        return self.tp + self.fp + self.fn + self.tn

    @property
    def accuracy(self) -> float:
        return (self.tp + self.tn) / self.n if self.n else float("nan")


def confusion_counts(pairs: Iterable[tuple[bool, bool]]) -> Confusion:
    """Counts over (replay_success, real_success) pairs."""
    c = {"tp": 0, "fp": 0, "fn": 0, "tn": 0}
    for rep, real in pairs:
        c[("t" if rep == real else "f") + ("p" if rep else "n")] += 1
    return Confusion(**c)


def replay_confusion(store: ResultsStore | str | Path, run_id: str | None = None, *,
                     by: str = "checkpoint") -> dict[tuple, Confusion]:
    """Confusion matrices from stored (replay, real) pairs: by="checkpoint" keys (task, policy,
    checkpoint), by="task" keys (task,). Replays that ended in an error are counted in `excluded`."""
    if by not in ("checkpoint", "task"):
        raise ValueError(f"by must be 'checkpoint' or 'task', got {by!r}")
    store = store if isinstance(store, ResultsStore) else ResultsStore(store)

    def ekey(r: EpisodeRecord):
        return (r.run_id, r.task, r.policy, r.checkpoint, r.init_state, r.seed)

    real = {ekey(r): r for r in store.episodes(run_id, domain="real")}
    groups: dict[tuple, list[tuple[bool, bool]]] = {}
    excluded: dict[tuple, int] = {}
    for rep in store.episodes(run_id, domain="replay"):
        k = ekey(rep)
        if k not in real:
            continue
        g = (rep.task, rep.policy, rep.checkpoint) if by == "checkpoint" else (rep.task,)
        groups.setdefault(g, [])
        if rep.status != "ok":
            excluded[g] = excluded.get(g, 0) + 1
            continue
        groups[g].append((rep.success, real[k].success))
    return {g: replace(confusion_counts(pairs), excluded=excluded.get(g, 0))
            for g, pairs in sorted(groups.items())}
