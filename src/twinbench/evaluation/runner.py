"""Parallel evaluation runner: every (policy, initial state) pair of a task, one committed episode each.

Episodes run in worker processes (spawn context; `workers=0` runs them in the calling process) or on
Ray (`backend="ray"`). The parent commits each finished episode to the results store at once, so a
re-run of the same run id skips finished episodes and an interrupted run (SIGINT, or SIGTERM handled the
same way) loses at most the episodes in flight. Status: "sim_error" when the env reports or raises a
simulation failure (or emits a non-finite state, or its worker process dies inside the episode: the run
goes on with a fresh process), "policy_error" when the policy raises or returns a malformed action.
Worker processes exit as soon as their parent dies, however it dies. The outcome is the env's
`info["is_success"]` at the episode's last step (the env's success rule, e.g. TwinEnv's "final" window
judgement or "early" termination, is stored in the episode's metrics).

Seeds: grid episodes use init_state i with seed `seed + i`; `episodes=N` samples N states, init_state
`n_grid_states + k` with seed `seed + k` (the env draws the state from that seed).
"""

from __future__ import annotations

import json
import os
import signal
import time
import traceback
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import numpy as np
from tyro.conf import UseAppendAction

from twinbench._runtime import quiet_warp, share_cores, watch_parent
from twinbench.errors import InputError, PolicyError
from twinbench.evaluation.export import policy_folder, write_eval_infos
from twinbench.evaluation.store import DEFAULT_DB, EpisodeRecord, ResultsStore, check_run_id
from twinbench.policies.spec import make_policy, parse_policy_spec
from twinbench.progress import progress_bar

RAY_HINT = "pip install 'twinbench[ray]'"


class EvaluationInterrupted(KeyboardInterrupt):
    """Raised by `evaluate` after SIGINT, once every finished episode is committed."""

    def __init__(self, message: str, done: int, total: int):
        super().__init__(message)
        self.message, self.done, self.total = message, done, total


@dataclass
class EpisodeOutcome:
    """What one rollout produced (before labelling it as an EpisodeRecord)."""

    success: bool
    status: str
    steps: int
    wall_time_s: float
    sum_reward: float = 0.0
    max_reward: float = 0.0
    error: str | None = None
    video_path: str | None = None
    started_at: float = 0.0
    success_rule: str | None = None  # the env's rule that judged the outcome (TwinEnv: "final" or "early")
    video_error: str | None = None  # why a requested video is missing (the episode itself is unaffected)

    def metrics(self, **extra) -> dict:
        """The EpisodeRecord.metrics of this outcome: `extra`, rewards, success rule, error text."""
        out = {**extra, "sum_reward": self.sum_reward, "max_reward": self.max_reward}
        if self.success_rule:
            out["success_rule"] = self.success_rule
        if self.error:
            out["error"] = self.error
        if self.video_error:
            out["video_error"] = self.video_error
        return out


@dataclass(frozen=True)
class EpisodeJob:
    """One episode to run: picklable, so it can travel to a worker process or a Ray task."""

    task: str
    policy: str  # spec string
    init_state: int
    seed: int
    run_id: str
    env_kwargs: dict = field(default_factory=dict)
    video_path: str | None = None


@dataclass(frozen=True)
class EpisodeBatch:
    """Episode jobs of one policy that one process runs together: one at a time in a TwinEnv when
    `worlds` is 1, else as the worlds of one `worlds`-world TwinVectorEnv (picklable, like EpisodeJob)."""

    jobs: tuple[EpisodeJob, ...]
    worlds: int = 1


def _error_text(err: BaseException) -> str:
    return "".join(traceback.format_exception_only(type(err), err)).strip()


class _VideoWriter:
    """Streams frames to an MP4 as they come (an episode's frames never sit in memory at once).

    A failing writer (disk full, ffmpeg error) never affects the episode: writing stops, `close()` reports
    the video as missing with the reason, and a file that is not a complete MP4 is deleted."""

    def __init__(self, path: str | Path, env):
        self.path = Path(path)
        self.fps = env.unwrapped.metadata.get("render_fps", 30)
        self._writer = None
        self.error: str | None = None

    def add(self, frame) -> None:
        if self.error is not None:
            return
        try:
            if self._writer is None:
                import imageio.v2 as imageio

                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._writer = imageio.get_writer(str(self.path), fps=self.fps)
            self._writer.append_data(np.asarray(frame))
        except Exception as err:  # noqa: BLE001 - a video failure is reported, not an episode failure
            self.error = f"writing {self.path}: {_error_text(err)}"

    def close(self) -> tuple[bool, str | None]:
        """Finish the file -> (whether a complete video was written, why not)."""
        if self._writer is None:
            return False, self.error
        try:
            self._writer.close()
        except Exception as err:  # noqa: BLE001
            self.error = self.error or f"finishing {self.path}: {_error_text(err)}"
        if self.error is None and not mp4_complete(self.path):
            self.error = f"{self.path} is truncated (incomplete MP4; disk full?)"
        if self.error is not None:
            self.path.unlink(missing_ok=True)
            warnings.warn(f"video missing: {self.error}", stacklevel=2)
            return False, self.error
        return True, None


def mp4_complete(path: str | Path) -> bool:
    """Whether `path` is a complete MP4: its top-level boxes tile the file exactly and include ftyp, mdat
    and moov (a file cut short by a full disk fails this)."""
    import struct

    path = Path(path)
    try:
        size, seen, pos = path.stat().st_size, set(), 0
        with path.open("rb") as fh:
            while pos < size:
                fh.seek(pos)
                head = fh.read(8)
                if len(head) < 8:
                    return False
                n, kind = struct.unpack(">I4s", head)
                if n == 1:
                    ext = fh.read(8)
                    if len(ext) < 8:
                        return False
                    n = struct.unpack(">Q", ext)[0]
                elif n == 0:
                    n = size - pos
                if n < 8 or pos + n > size:
                    return False
                seen.add(kind)
                pos += n
    except OSError:
        return False
    return {b"ftyp", b"mdat", b"moov"} <= seen


def policy_observation(policy, obs: dict, info: dict) -> dict:
    """The observation `policy` is given: `obs`, plus the privileged `environment_state` from
    `info["privileged"]` for policies that declare `uses_environment_state` (scripted experts)."""
    if not getattr(policy, "uses_environment_state", False) or "environment_state" in obs:
        return obs
    privileged = info.get("privileged") or {}
    if "environment_state" not in privileged:
        raise PolicyError("this policy needs the task's environment_state, which the env does not provide")
    return {**obs, "environment_state": privileged["environment_state"]}


class _Rollout:
    """One episode's bookkeeping, driven step by step by `run_episode` (one env) or `run_worlds` (the worlds
    of a vector env): policy calls and their checks, env failures, rewards, the video, the outcome."""

    def __init__(self, env, policy, *, init_state: int, seed: int, max_steps: int | None = None,
                 video_path: str | Path | None = None):
        self.env, self.policy, self.init_state, self.seed = env, policy, int(init_state), int(seed)
        self.t0, self.started = time.perf_counter(), time.time()
        self.rewards: list[float] = []
        self.video_path = video_path
        self.video = _VideoWriter(video_path, env) if video_path is not None else None
        self.success, self.status, self.error, self.steps, self.rule = False, "ok", None, 0, None
        self.limit = int(max_steps or getattr(env.unwrapped, "_max_episode_steps", 0) or 0)
        if self.limit <= 0:
            raise ValueError("run_episode: env has no _max_episode_steps; pass max_steps")
        self.ended = False

    def start(self) -> None:
        """Reset the env to this episode's initial state and the policy to its seed."""
        try:
            self.obs, self.info = self.env.reset(seed=self.seed, options={"init_state": self.init_state})
            if self.video is not None:
                self.video.add(self.env.render())
        except Exception as err:  # noqa: BLE001 - any env failure is a sim_error, reported with its text
            self._end("sim_error", f"reset: {_error_text(err)}")
            return
        try:
            if hasattr(self.policy, "reseed"):
                self.policy.reseed(self.seed)
            else:
                self.policy.reset()
        except Exception as err:  # noqa: BLE001
            self._end("policy_error", f"reset: {_error_text(err)}")

    def action(self) -> np.ndarray | None:
        """The policy's next action, or None once the episode has ended (a policy failure ends it)."""
        if self.ended:
            return None
        if self.steps >= self.limit:
            self.ended = True
            return None
        shape = self.env.action_space.shape
        try:
            obs = policy_observation(self.policy, self.obs, self.info)
            action = np.asarray(self.policy.select_action(obs), dtype=np.float64)
            if action.shape != shape or not np.all(np.isfinite(action)):
                raise PolicyError(f"action of shape {action.shape} (expected {shape}) "
                                  f"or non-finite: {action}")
        except Exception as err:  # noqa: BLE001
            self._end("policy_error", _error_text(err))
            return None
        return action.astype(self.env.action_space.dtype)

    def observe(self, result) -> None:
        """Take the env's step result (obs, reward, terminated, truncated, info) or the error it raised."""
        if isinstance(result, BaseException):
            self._end("sim_error", _error_text(result))
            return
        self.obs, reward, terminated, truncated, self.info = result
        self.steps += 1
        self.rewards.append(float(reward))
        env_status = self.info.get("status", "ok")
        if env_status != "ok":
            self._end("sim_error", f"env status {env_status!r} at step {self.steps}")
            return
        if not np.all(np.isfinite(np.asarray(self.obs["agent_pos"], dtype=np.float64))):
            self._end("sim_error", f"non-finite agent_pos at step {self.steps}")
            return
        self.success = bool(self.info.get("is_success", False))  # the final frame's judgement
        self.rule = self.info.get("success_rule", self.rule)
        if self.video is not None:
            self.video.add(self.env.render())
        if terminated or truncated or self.steps >= self.limit:
            self.ended = True

    def _end(self, status: str, error: str) -> None:
        self.status, self.error, self.ended = status, error, True

    def outcome(self) -> EpisodeOutcome:
        written, video_error = self.video.close() if self.video is not None else (False, None)
        r = self.rewards
        return EpisodeOutcome(
            success=self.success and self.status == "ok", status=self.status, steps=self.steps,
            wall_time_s=time.perf_counter() - self.t0, sum_reward=float(np.sum(r)) if r else 0.0,
            max_reward=float(np.max(r)) if r else 0.0, error=self.error,
            video_path=str(self.video_path) if written else None, started_at=self.started,
            success_rule=self.rule, video_error=video_error,
        )


def run_episode(env, policy, *, init_state: int, seed: int, max_steps: int | None = None,
                video_path: str | Path | None = None) -> EpisodeOutcome:
    """Roll `policy` out in `env` from `init_state`; never raises for env or policy failures."""
    r = _Rollout(env, policy, init_state=init_state, seed=seed, max_steps=max_steps, video_path=video_path)
    r.start()
    while (action := r.action()) is not None:
        try:
            result = env.step(action)
        except Exception as err:  # noqa: BLE001 - any env failure is a sim_error, reported with its text
            result = err
        r.observe(result)
    return r.outcome()


def run_worlds(vec_env, policies: list, episodes: list[tuple[int, int, str | None]]) -> list[EpisodeOutcome]:
    """Roll out `episodes` [(init_state, seed, video_path)] in the worlds of `vec_env` (a TwinVectorEnv),
    world i with `policies[i]`, all worlds in one physics frame per step. Each episode's outcome is the
    one `run_episode` gives in a one-world env (same steps, rewards and judgement, bit for bit on CPU);
    a world whose episode ends waits, held, until every episode has ended. Never raises for env or
    policy failures."""
    if len(episodes) > vec_env.num_envs or len(policies) < len(episodes):
        raise ValueError(f"run_worlds: {len(episodes)} episodes for {vec_env.num_envs} worlds and "
                         f"{len(policies)} policies")
    rollouts = [
        _Rollout(vec_env.envs[i], policies[i], init_state=s, seed=seed, video_path=video)
        for i, (s, seed, video) in enumerate(episodes)
    ]
    for r in rollouts:
        r.start()
    while True:
        actions = [r.action() for r in rollouts]
        if all(a is None for a in actions):
            break
        try:
            results = vec_env.step_worlds(actions + [None] * (vec_env.num_envs - len(rollouts)))
        except Exception as err:  # noqa: BLE001 - a failure of the shared frame ends every running episode
            results = [err] * len(rollouts)
        for r, a, result in zip(rollouts, actions, results, strict=False):
            if a is not None:
                r.observe(result)
    return [r.outcome() for r in rollouts]


# ---- worker side -----------------------------------------------------------------------------------
_CACHE: dict = {}  # per process: envs by (task, env_kwargs), policies by (task, spec)


def run_job(job: EpisodeJob) -> EpisodeRecord:
    """Run one episode job (in a worker or in-process), reusing this process's env and policy."""
    from twinbench.tasks import get_task

    task = get_task(job.task)
    spec = parse_policy_spec(job.policy)
    env_key = (job.task, json.dumps(job.env_kwargs, sort_keys=True))
    if env_key not in _CACHE:
        try:
            _CACHE[env_key] = task.make_env(**job.env_kwargs)
        except TypeError as err:  # an unknown keyword in --env-kwargs
            raise InputError(f"--env-kwargs {json.dumps(job.env_kwargs)}: the {job.task!r} env does not "
                             f"accept them ({err})") from None
    env = _CACHE[env_key]
    pol_key = (job.task, job.policy)
    policy, build_error = _CACHE.get(pol_key), None
    if policy is None:
        try:
            policy = make_policy(spec, task, env, seed=job.seed)
            _CACHE[pol_key] = policy
        except Exception as err:  # noqa: BLE001 - a policy that cannot be built is a policy_error
            build_error = f"building policy {job.policy!r}: {_error_text(err)}"
    if policy is None:
        out = EpisodeOutcome(False, "policy_error", 0, 0.0, error=build_error, started_at=time.time())
    else:
        out = run_episode(env, policy, init_state=job.init_state, seed=job.seed, video_path=job.video_path)
    return _record(job, out)


def _record(job: EpisodeJob, out: EpisodeOutcome) -> EpisodeRecord:
    spec = parse_policy_spec(job.policy)
    return EpisodeRecord(
        run_id=job.run_id, task=job.task, policy=spec.name, checkpoint=spec.checkpoint,
        train_step=spec.train_step, init_state=job.init_state, seed=job.seed, domain="sim",
        success=out.success, status=out.status, steps=out.steps, wall_time_s=out.wall_time_s,
        video_path=out.video_path, metrics=out.metrics(started_at=out.started_at),
    )


def run_batch(batch: EpisodeBatch) -> list[EpisodeRecord]:
    """Run a batch (in a worker or in-process): one job at a time, or its jobs as the worlds of one
    many-world env (this process keeps the env and one policy per world for the next batch)."""
    from twinbench.tasks import get_task

    if batch.worlds == 1:
        return [run_job(job) for job in batch.jobs]
    first = batch.jobs[0]
    if len(batch.jobs) > batch.worlds or any(
        (j.task, j.policy, j.env_kwargs) != (first.task, first.policy, first.env_kwargs) for j in batch.jobs
    ):
        raise ValueError("an EpisodeBatch holds at most `worlds` jobs of one task, policy and env kwargs")
    task = get_task(first.task)
    env_key = (first.task, json.dumps(first.env_kwargs, sort_keys=True), "worlds", batch.worlds)
    if env_key not in _CACHE:
        try:
            _CACHE[env_key] = task.make_vector_env(batch.worlds, **first.env_kwargs)
        except TypeError as err:  # an unknown keyword in --env-kwargs
            raise InputError(f"--env-kwargs {json.dumps(first.env_kwargs)}: the {first.task!r} env does not "
                             f"accept them ({err})") from None
    vec = _CACHE[env_key]
    policies = []
    for i, job in enumerate(batch.jobs):
        key = (job.task, job.policy, "world", i)
        if key not in _CACHE:
            try:
                _CACHE[key] = make_policy(parse_policy_spec(job.policy), task, vec.envs[i], seed=job.seed)
            except Exception as err:  # noqa: BLE001 - a policy that cannot be built is a policy_error
                error = f"building policy {job.policy!r}: {_error_text(err)}"
                return [_record(j, EpisodeOutcome(False, "policy_error", 0, 0.0, error=error,
                                                  started_at=time.time())) for j in batch.jobs]
        policies.append(_CACHE[key])
    outs = run_worlds(vec, policies, [(j.init_state, j.seed, j.video_path) for j in batch.jobs])
    return [_record(j, out) for j, out in zip(batch.jobs, outs, strict=True)]


# ---- parent side -----------------------------------------------------------------------------------
def episode_set(n_grid_states: int, episodes: str | int, seed: int) -> list[tuple[int, int]]:
    """[(init_state, seed)] for `episodes` = "grid", "grid:I,J,..." (a subset of the grid) or a number N
    of sampled states."""
    if episodes == "grid":
        return [(i, seed + i) for i in range(n_grid_states)]
    if isinstance(episodes, str) and episodes.startswith("grid:"):
        try:
            chosen = [int(v) for v in episodes[5:].split(",")]
        except ValueError:
            raise ValueError(f"episodes 'grid:I,J,...' needs integer grid indices, "
                             f"got {episodes!r}") from None
        bad = [i for i in chosen if not 0 <= i < n_grid_states]
        if bad or len(set(chosen)) != len(chosen):
            raise ValueError(f"episodes {episodes!r}: indices must be distinct and in [0, {n_grid_states}), "
                             f"got {chosen}")
        return [(i, seed + i) for i in chosen]
    try:
        n = int(episodes)
    except (TypeError, ValueError):
        raise ValueError(f"episodes must be 'grid', 'grid:I,J,...' or a positive integer, "
                         f"got {episodes!r}") from None
    if n < 1:
        raise ValueError(f"episodes must be 'grid', 'grid:I,J,...' or a positive integer, got {episodes!r}")
    if n > MAX_EPISODES:
        raise InputError(f"--episodes {n}: at most {MAX_EPISODES} sampled episodes per run; split the "
                         "evaluation into several runs")
    return [(n_grid_states + k, seed + k) for k in range(n)]


def _versions() -> dict:
    import gymnasium
    import warp

    import twinbench

    return {"twinbench": twinbench.__version__, "gymnasium": gymnasium.__version__, "numpy": np.__version__,
            "warp": warp.config.version}


def _run_local(batches: list[EpisodeBatch], workers: int, on_done) -> None:
    if workers == 0:
        try:
            for batch in batches:
                for rec in run_batch(batch):
                    on_done(rec)
        finally:
            close_cached_policies()
        return
    _run_pool(batches, workers, on_done)


def _import_ray():
    try:
        import ray
    except ImportError as err:
        raise ImportError(f"--backend ray needs the 'ray' extra ({RAY_HINT})") from err
    return ray


def _run_ray(batches: list[EpisodeBatch], workers: int, on_done) -> None:
    ray = _import_ray()
    if not ray.is_initialized():
        ray.init(num_cpus=workers if workers > 0 else None, include_dashboard=False)
    # one CPU per task: a task's physics stays on one core (no split frames competing for cores)
    env_vars = {"TWINBENCH_CPU_THREADS": os.environ.get("TWINBENCH_CPU_THREADS", "1")}
    remote_batch = ray.remote(num_cpus=1, max_retries=0, runtime_env={"env_vars": env_vars})(run_batch)
    by_ref = {remote_batch.remote(batch): batch for batch in batches}
    pending = list(by_ref)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            try:
                recs = ray.get(done[0])
            except (ray.exceptions.WorkerCrashedError, ray.exceptions.NodeDiedError) as err:
                recs = [crash_record(job, f"the Ray worker died during the episode ({err})")
                        for job in by_ref[done[0]].jobs]
            for rec in recs:
                on_done(rec)
    except BaseException:
        for ref in pending:
            ray.cancel(ref, force=True)
        raise


def evaluate(task: str, policies: Sequence[str], episodes: str | int = "grid", workers: int = 1,
             run_id: str = "eval", store: ResultsStore | str | Path = DEFAULT_DB, *, seed: int = 0,
             video: bool = False, backend: str = "local", output_dir: str | Path = "outputs",
             env_kwargs: dict | None = None, retry_errors: bool = False, progress: bool = False,
             write_eval_info: bool = True, log=None, worlds: int = 1) -> list[EpisodeRecord]:
    """Evaluate `policies` (spec strings) on `task`; returns the run's records (old and new) in job order.

    `worlds` > 1 runs each policy's episodes `worlds` at a time as the worlds of one many-world env
    (same outcomes as one at a time), in each of the `workers` processes.

    Finished episodes of `run_id` already in `store` are skipped (episodes that ended in an error
    too, unless `retry_errors`). On SIGINT raises `EvaluationInterrupted` after committing every
    finished episode. Writes `<output_dir>/eval/<run_id>/<policy>/eval_info.json` per policy.
    """
    from twinbench.tasks import get_task

    spec_task = get_task(task)
    if backend not in ("local", "ray"):
        raise ValueError(f"backend must be 'local' or 'ray', got {backend!r}")
    _check_counts(workers, seed)
    if isinstance(worlds, bool) or not isinstance(worlds, int) or not 1 <= worlds <= MAX_WORLDS:
        raise InputError(f"--worlds {worlds}: must be an integer between 1 and {MAX_WORLDS}")
    if worlds > 1 and spec_task.task_cls is None:
        raise InputError(f"--worlds {worlds}: task {task!r} has its own env, not a twin; use --worlds 1")
    if not policies:
        raise ValueError("give at least one policy spec (e.g. 'expert')")
    check_run_id(run_id)  # a name, never a path: it names folders under output_dir
    specs = [parse_policy_spec(p) for p in policies]
    keys = [(s.name, s.checkpoint) for s in specs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"policies {list(policies)} map to duplicate (policy, checkpoint) labels {keys}; "
                         "give distinct specs or names (NAME=SPEC)")
    env_kwargs = dict(env_kwargs or {})
    states = episode_set(spec_task.n_grid_states, episodes, int(seed))
    store = store if isinstance(store, ResultsStore) else ResultsStore(store)
    protocol = {"task": task, "episodes": episodes if str(episodes).startswith("grid") else int(episodes),
                "init_states": [i for i, _ in states], "seeds": [s for _, s in states],
                "policies": list(policies), "base_seed": int(seed), "env_kwargs": env_kwargs,
                "env_id": spec_task.env_id, "versions": _versions()}
    store.start_run(run_id, task, protocol)
    out_dir = Path(output_dir)
    jobs: dict[tuple[str, str, int, int], EpisodeJob] = {}  # by (policy, checkpoint, init_state, seed)
    for spec in specs:
        for init_state, s in states:
            video_path = None
            if video:
                folder = out_dir / "videos" / run_id / policy_folder(spec.name, spec.checkpoint)
                video_path = str(folder / f"init{init_state}_seed{s}.mp4")
            jobs[(spec.name, spec.checkpoint, init_state, s)] = EpisodeJob(
                task, spec.spec, init_state, s, run_id, env_kwargs, video_path)
    existing = {(r.policy, r.checkpoint, r.init_state, r.seed): r
                for r in store.episodes(run_id, domain="sim")}
    skip = {k for k, r in existing.items() if r.status == "ok" or not retry_errors}
    todo = [j for k, j in jobs.items() if k not in skip]
    log = log or (lambda msg: None)
    batches: list[EpisodeBatch] = []
    for job in todo:  # todo is grouped by policy: consecutive jobs of one policy share a batch
        last = batches[-1] if batches else None
        if last is not None and len(last.jobs) < worlds and last.jobs[0].policy == job.policy:
            batches[-1] = EpisodeBatch((*last.jobs, job), worlds)
        else:
            batches.append(EpisodeBatch((job,), worlds))
    log(f"run {run_id!r}: {len(jobs)} episodes, {len(jobs) - len(todo)} already finished, {len(todo)} to run "
        f"({backend}, {workers} worker{'s' if workers != 1 else ''}"
        f"{f', {worlds} worlds per env' if worlds > 1 else ''})")
    results = {k: existing[k] for k in skip}
    done_count = [len(jobs) - len(todo)]

    with progress_bar(progress) as bar:
        bar_task = bar.add_task(f"eval {run_id}", total=len(jobs), completed=done_count[0])

        def on_done(rec: EpisodeRecord) -> None:
            store.record_episode(rec)
            results[(rec.policy, rec.checkpoint, rec.init_state, rec.seed)] = rec
            done_count[0] += 1
            bar.advance(bar_task)

        try:
            with _sigterm_as_interrupt():
                if backend == "ray":
                    _run_ray(batches, int(workers), on_done)
                else:
                    _run_local(batches, int(workers), on_done)
        except KeyboardInterrupt as err:
            left = len(jobs) - done_count[0]
            what, exc = ("terminated (SIGTERM)", EvaluationTerminated) if isinstance(err, _SigTerm) else (
                "interrupted", EvaluationInterrupted)
            msg = (f"{what}: {done_count[0]} of {len(jobs)} episodes of run {run_id!r} are in "
                   f"{store.path}; re-run the same command (same --run-id) to resume the remaining {left}")
            raise exc(msg, done_count[0], len(jobs)) from None
    missing = [r for r in results.values() if r.metrics.get("video_error")]
    for r in missing:
        log(f"warning: video missing for {r.policy} init_state {r.init_state} seed {r.seed}: "
            f"{r.metrics['video_error']}")
    records = [results[k] for k in jobs]
    if write_eval_info:
        write_eval_infos(records, out_dir / "eval" / run_id)
    return records


# ---- CLI -------------------------------------------------------------------------------------------
def parse_env_kwargs(text: str) -> dict:
    """The `--env-kwargs` option: a JSON object of extra gymnasium.make keyword arguments ("" = none)."""
    try:
        env_kwargs = json.loads(text) if text else {}
    except json.JSONDecodeError as err:
        raise ValueError(f"--env-kwargs must be a JSON object, e.g. '{{\"step_delay_s\": 0.01}}': "
                         f"{err}") from err
    if not isinstance(env_kwargs, dict):
        raise ValueError("--env-kwargs must be a JSON object (dict)")
    return env_kwargs


def env_kwargs_with_twin(env_kwargs: dict, twin: Path | None) -> dict:
    """`--twin DIR`: evaluate in the twin directory DIR (an absolute path, so worker processes find it)."""
    if twin is None:
        return env_kwargs
    if "twin" in env_kwargs:
        raise ValueError("give the twin either as --twin or in --env-kwargs, not both")
    if not (Path(twin) / "twin.json").is_file():
        raise ValueError(f"--twin {twin}: no twin.json there (write one with `twinbench twin export` "
                         "or the construction tools)")
    return {**env_kwargs, "twin": str(Path(twin).resolve())}


@dataclass(frozen=True)
class EvalConfig:
    """Evaluate policies on a task over its initial-state grid (or N sampled states)."""

    run_id: str
    """evaluation run id; re-running the same id resumes it"""
    task: str = "push-t"
    """task name (twinbench.tasks): push-t, rope-routing, toy-packing, point-reach (a cheap debug task)"""
    policy: Annotated[tuple[str, ...], UseAppendAction] = ()  # repeatable: --policy a --policy b
    """policy spec, repeatable: expert, expert@LEVEL, remote:ws://HOST:PORT, lerobot:PATH, NAME=SPEC"""
    episodes: str = "grid"
    """'grid' (the task's initial-state grid), 'grid:I,J,...' (some grid states) or N (N sampled states)"""
    workers: int = 1
    """worker processes (0 = run in this process)"""
    db: Path = DEFAULT_DB
    video: bool = False
    """write an MP4 per episode under OUTPUT_DIR/videos/RUN_ID/"""
    backend: Literal["local", "ray"] = "local"
    seed: int = 0
    output_dir: Path = Path("outputs")
    env_kwargs: str = ""
    """JSON dict of extra gymnasium.make keyword arguments for the task's env"""
    twin: Path | None = None
    """a twin directory to evaluate in (default: the task's built-in cell)"""
    worlds: int = 1
    """episodes run together as worlds of one many-world env (one physics launch for all), per worker"""
    retry_errors: bool = False
    """re-run episodes that ended in sim_error/policy_error"""
    progress: bool = True


def main(cfg: EvalConfig) -> int:
    from rich.console import Console

    console = Console(stderr=True)

    def say(msg: str) -> None:
        console.print(msg, markup=False, soft_wrap=True, highlight=False)

    if not cfg.policy:
        say("twinbench eval: give at least one --policy (e.g. --policy expert)")
        return 2
    env_kwargs = env_kwargs_with_twin(parse_env_kwargs(cfg.env_kwargs), cfg.twin)
    try:
        records = evaluate(cfg.task, list(cfg.policy), cfg.episodes, cfg.workers, cfg.run_id, cfg.db,
                           seed=cfg.seed, video=cfg.video, backend=cfg.backend, output_dir=cfg.output_dir,
                           env_kwargs=env_kwargs, retry_errors=cfg.retry_errors, progress=cfg.progress,
                           log=say, worlds=cfg.worlds)
    except EvaluationInterrupted as err:
        say(err.message)
        return 143 if isinstance(err, EvaluationTerminated) else 130
    by_policy: dict[tuple[str, str], list[EpisodeRecord]] = {}
    for r in records:
        by_policy.setdefault((r.policy, r.checkpoint), []).append(r)
    for (name, ckpt), recs in by_policy.items():
        ok = sum(r.success for r in recs)
        errs = sum(r.status != "ok" for r in recs)
        label = name + (f" [{ckpt}]" if ckpt else "")
        say(f"{label}: {ok}/{len(recs)} successes ({100 * ok / len(recs):.1f}%), {errs} errors")
    say(f"eval_info.json files under {cfg.output_dir / 'eval' / cfg.run_id}")
    return 0


# ---- hardening: worker processes that die with their parent, crashes recorded, SIGTERM like Ctrl-C -----
MAX_EPISODES = 100_000  # per policy and run; more is refused before anything is allocated
MAX_WORKERS = 256
MAX_WORLDS = 1024


def _check_counts(workers, seed) -> None:
    """--workers and --seed, checked before anything starts (InputError naming the option)."""
    if not 0 <= int(workers) <= MAX_WORKERS:
        raise InputError(f"--workers {workers}: must be between 0 (run in this process) and {MAX_WORKERS}")
    if not 0 <= int(seed) <= 2**62:
        raise InputError(f"--seed {seed}: must be between 0 and 2**62")


class EvaluationTerminated(EvaluationInterrupted):
    """Raised by `evaluate` after SIGTERM (handled like Ctrl-C: every finished episode is committed)."""


class _SigTerm(KeyboardInterrupt):
    """Raised in the main thread by the SIGTERM handler, so SIGTERM takes Ctrl-C's path."""


class _sigterm_as_interrupt:
    """Context manager: while active (main thread only), SIGTERM raises _SigTerm."""

    def __enter__(self):
        import threading

        self._old = None
        if threading.current_thread() is threading.main_thread():
            def handler(signum, frame):
                raise _SigTerm("SIGTERM")

            self._old = signal.signal(signal.SIGTERM, handler)
        return self

    def __exit__(self, *exc) -> None:
        if self._old is not None:
            signal.signal(signal.SIGTERM, self._old)


def close_cached_policies() -> None:
    """Close and forget this process's cached policies (a remote policy's connection is closed here, not
    from `__del__` at interpreter shutdown, where closing it could hang). Cached envs are kept."""
    for key in [k for k, v in _CACHE.items() if hasattr(v, "select_action")]:
        policy = _CACHE.pop(key)
        close = getattr(policy, "close", None)
        if callable(close):
            try:
                close()
            except Exception:  # noqa: BLE001 - closing is best effort
                pass


def crash_record(job: EpisodeJob, reason: str) -> EpisodeRecord:
    """The record of an episode whose process died: status sim_error, with the reason."""
    spec = parse_policy_spec(job.policy)
    out = EpisodeOutcome(False, "sim_error", 0, 0.0, error=reason, started_at=time.time())
    return EpisodeRecord(
        run_id=job.run_id, task=job.task, policy=spec.name, checkpoint=spec.checkpoint,
        train_step=spec.train_step, init_state=job.init_state, seed=job.seed, domain="sim",
        success=False, status="sim_error", steps=0, wall_time_s=0.0, video_path=None,
        metrics=out.metrics(started_at=out.started_at),
    )


def _exit_reason(exitcode: int | None) -> str:
    if exitcode is not None and exitcode < 0:
        try:
            return f"killed by signal {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


def _worker_main(conn, cores: str = "1") -> None:
    """A worker process: runs one EpisodeBatch at a time from `conn`, replies ("ok", records) or
    ("error", exc).

    Ignores SIGINT and SIGTERM (the parent decides: commit finished episodes, kill the rest) and exits
    as soon as the parent dies."""
    import pickle

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_IGN)
    os.environ["TWINBENCH_CPU_THREADS"] = cores  # this worker's share of the cores (see share_cores)
    watch_parent()
    quiet_warp()  # workers print no Warp banner or module-load lines either
    try:
        while True:
            try:
                job = conn.recv()
            except (EOFError, OSError):
                return
            if job is None:
                return
            try:
                reply = ("ok", run_batch(job))
            except BaseException as err:  # noqa: BLE001 - sent to the parent, which raises it
                try:
                    pickle.dumps(err)
                except Exception:  # noqa: BLE001
                    err = RuntimeError(_error_text(err))
                reply = ("error", err)
            conn.send(reply)
    finally:
        close_cached_policies()


class _Worker:
    def __init__(self, ctx, cores: str):
        self.conn, child = ctx.Pipe(duplex=True)
        self.process = ctx.Process(target=_worker_main, args=(child, cores), daemon=True,
                                   name="twinbench-worker")
        self.process.start()
        child.close()
        self.job: EpisodeBatch | None = None

    def stop(self, graceful: bool) -> None:
        if graceful and self.job is None and self.process.is_alive():
            try:
                self.conn.send(None)
            except OSError:
                pass
            self.process.join(timeout=5)
        if self.process.is_alive():
            self.process.kill()  # SIGKILL: workers ignore SIGTERM
            self.process.join(timeout=5)
        self.conn.close()


def _run_pool(jobs: list[EpisodeBatch], workers: int, on_done) -> None:
    """Run the batches `jobs` on `workers` spawned processes, one batch per process at a time, so that a
    process that dies (segfault, os._exit, OOM kill) is known to have died in its batch: its episodes are
    recorded as sim_error with the reason, a fresh process takes its place and the run goes on. An
    exception raised by run_batch itself (bad input) stops the run and is re-raised here."""
    import multiprocessing as mp
    from collections import deque
    from multiprocessing.connection import wait

    ctx = mp.get_context("spawn")
    cores = share_cores(workers)
    todo = deque(jobs)
    pool: list[_Worker] = []
    ok = False
    try:
        while todo or any(w.job is not None for w in pool):
            pool = [w for w in pool if w.job is not None or w.process.is_alive()]
            while todo and len(pool) < workers and sum(w.job is None for w in pool) < len(todo):
                pool.append(_Worker(ctx, cores))
            for w in pool:
                if w.job is None and todo:
                    w.job = todo.popleft()
                    w.conn.send(w.job)
            busy = [w for w in pool if w.job is not None]
            ready = set(wait([w.conn for w in busy] + [w.process.sentinel for w in busy]))
            for w in pool:
                if w.job is None or not (w.conn in ready or w.process.sentinel in ready):
                    continue
                reply = None
                try:
                    if w.conn.poll():
                        reply = w.conn.recv()
                except (EOFError, OSError):
                    reply = None
                if reply is None:  # the process died inside the episode
                    w.process.join(timeout=5)
                    batch = w.job
                    w.job = None
                    w.stop(graceful=False)
                    for job in batch.jobs:
                        on_done(crash_record(job, f"worker process died during the episode "
                                                  f"({_exit_reason(w.process.exitcode)})"))
                    continue  # replaced at the top of the loop
                w.job = None
                kind, value = reply
                if kind == "error":
                    raise value
                for rec in value:
                    on_done(rec)
        ok = True
    finally:
        for w in pool:
            w.stop(graceful=ok)
