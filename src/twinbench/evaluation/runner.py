"""Evaluation runs: every (policy, initial state) pair of a task, one committed episode each (`evaluate`).

Episodes run in worker processes (spawn context; `workers=0` runs them in the calling process) or on
Ray (`backend="ray"`), see `evaluation.backends`; one episode is `evaluation.rollout`. The parent commits
each finished episode to the results store at once, so a re-run of the same run id skips finished
episodes and an interrupted run (SIGINT, or SIGTERM handled the same way) loses at most the episodes in
flight. A worker process that dies inside an episode records it as "sim_error" and the run goes on with a
fresh process. Videos are written under a temporary name and renamed once complete; the temporary files
of episodes in flight are removed when a run is interrupted (and before a resumed run starts), so no
partial MP4 is left behind.

Seeds: grid episodes use init_state i with seed `seed + i`; `episodes=N` samples N states, init_state
`n_grid_states + k` with seed `seed + k` (the env draws the state from that seed).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from twinbench.errors import InputError, StorageError
from twinbench.evaluation.backends import (
    SigTerm,
    refuse_in_worker_import,
    run_local,
    run_ray,
    sigterm_as_interrupt,
)
from twinbench.evaluation.export import policy_folder, write_eval_infos
from twinbench.evaluation.grids import grid_info
from twinbench.evaluation.rollout import EpisodeBatch, EpisodeJob
from twinbench.evaluation.store import DEFAULT_DB, EpisodeRecord, ResultsStore, check_run_id
from twinbench.evaluation.video import ALL_VIEWS, partial_path
from twinbench.policies.spec import parse_policy_spec
from twinbench.progress import ProgressLines, progress_bar

MAX_EPISODES = 100_000  # per policy and run; more is refused before anything is allocated
MAX_WORKERS = 256
MAX_WORLDS = 1024


class EvaluationInterrupted(KeyboardInterrupt):
    """Raised by `evaluate` after SIGINT, once every finished episode is committed."""

    def __init__(self, message: str, done: int, total: int):
        super().__init__(message)
        self.message, self.done, self.total = message, done, total


class EvaluationTerminated(EvaluationInterrupted):
    """Raised by `evaluate` after SIGTERM (handled like Ctrl-C: every finished episode is committed)."""


def _check_counts(workers, seed) -> None:
    """--workers and --seed, checked before anything starts (InputError naming the option)."""
    if not 0 <= int(workers) <= MAX_WORKERS:
        raise InputError(f"--workers {workers}: must be between 0 (run in this process) and {MAX_WORKERS}")
    if not 0 <= int(seed) <= 2**62:
        raise InputError(f"--seed {seed}: must be between 0 and 2**62")


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


def actions_file(output_dir: str | Path, run_id: str, policy: str, checkpoint: str, init_state: int,
                 seed: int) -> Path:
    """Where `evaluate(..., record_actions=True)` puts an episode's commanded actions."""
    return (Path(output_dir) / "actions" / run_id / policy_folder(policy, checkpoint)
            / f"init{init_state}_seed{seed}.npy")


def _remove_partial_videos(jobs) -> None:
    for job in jobs:
        if job.video_path is not None:
            partial_path(job.video_path).unlink(missing_ok=True)


def _stored_policies(store: ResultsStore, run_id: str) -> list[str]:
    """The policy specs run `run_id` was started (or extended) with; [] for a new run."""
    try:
        return list(store.run_protocol(run_id).get("policies", []))
    except KeyError:
        return []


def _parsed(specs) -> list:
    """The specs that parse (a stored one from an older grammar may not: it then names no label)."""
    out = []
    for text in specs:
        try:
            out.append(parse_policy_spec(text))
        except (ValueError, InputError):
            pass
    return out


def _twin_hash(task: str, env_kwargs: dict, run_id: str, store: ResultsStore) -> str:
    """The content hash of the twin the run evaluates on: the twin directory `env_kwargs["twin"]`, or the
    task's built-in cell as `env_kwargs` build it; InputError when run `run_id` was started on a twin with
    other content (resuming would mix two twins' outcomes)."""
    import inspect
    import json

    from twinbench.env import TwinEnv, resolve_task_twin
    from twinbench.twin.files import twin_dir_hash, twin_spec_hash

    twin = env_kwargs.get("twin")
    if twin is not None:
        now = twin_dir_hash(twin)
        what, changed, fix = f"the twin {twin}", "its files have changed since", "restore the twin's files"
    else:  # the built-in cell, from the keyword arguments that gymnasium.make and TwinEnv pass on as settings
        import gymnasium

        named = {*inspect.signature(TwinEnv.__init__).parameters,
                 *inspect.signature(gymnasium.make).parameters}
        settings = {k: v for k, v in env_kwargs.items() if k not in named}
        try:
            _, spec = resolve_task_twin(task, None, env_kwargs.get("preset", "reference"),
                                        env_kwargs.get("roles"), settings)
        except (TypeError, ValueError) as err:
            raise InputError(f"--env-kwargs {json.dumps(env_kwargs)}: {err}") from None
        now = twin_spec_hash(spec)
        what, changed, fix = (f"task {task!r}'s built-in cell", "the cell the code builds has changed "
                              "since", "go back to the code that built it")
    try:
        before = store.run_protocol(run_id).get("twin_hash")
    except KeyError:  # a new run
        return now
    if before is not None and before != now:
        raise InputError(f"run {run_id!r} in {store.path} was evaluated on {what} with content hash "
                         f"{before[:12]}..., {changed} (now {now[:12]}...); use a new --run-id for the "
                         f"changed twin, or {fix} to resume")
    return now


def add_run_seconds_quietly(store: ResultsStore, run_id: str, seconds: float) -> None:
    """`store.add_run_seconds`, except that a store that cannot be written (a full disk) loses the time
    rather than hiding the error the run is ending with."""
    try:
        store.add_run_seconds(run_id, seconds)
    except (StorageError, InputError):
        pass


def moved_twin_keys(store: ResultsStore, run_id: str, protocol: dict) -> tuple[str, ...]:
    """("env_kwargs",) when run `run_id` was started on the same twin (equal `twin_hash`) at another path,
    with its other env settings equal: a moved study or results folder, or a twin named relative to
    another directory. The protocol may then take the new path (a `grow` key of `start_run`)."""
    try:
        old = store.run_protocol(run_id)
    except KeyError:
        return ()
    before, now = dict(old.get("env_kwargs") or {}), dict(protocol.get("env_kwargs") or {})
    moved = before.pop("twin", None) != now.pop("twin", None)
    same = old.get("twin_hash") is not None and old.get("twin_hash") == protocol.get("twin_hash")
    return ("env_kwargs",) if moved and same and before == now else ()


def _versions() -> dict:
    import gymnasium
    import warp

    import twinbench

    return {"twinbench": twinbench.__version__, "gymnasium": gymnasium.__version__, "numpy": np.__version__,
            "warp": warp.config.version}


def evaluate(task: str, policies: Sequence[str], episodes: str | int = "grid", workers: int = 1,
             run_id: str = "eval", store: ResultsStore | str | Path = DEFAULT_DB, *, seed: int = 0,
             video: bool = False, backend: str = "local", output_dir: str | Path = "outputs",
             env_kwargs: dict | None = None, retry_errors: bool = False, progress: bool = False,
             write_eval_info: bool = True, log=None, worlds: int = 1, video_views: str = ALL_VIEWS,
             policy_timeout_s: float | None = None, record_actions: bool = False) -> list[EpisodeRecord]:
    """Evaluate `policies` (spec strings) on `task`; returns the run's records (old and new) in job order.

    `worlds` > 1 runs each policy's episodes `worlds` at a time as the worlds of one many-world env
    (same outcomes as one at a time), in each of the `workers` processes. `video_views`: the cameras
    each video shows side by side ("all", or names joined by "+"). `policy_timeout_s`: seconds per
    policy call, for policies with a `timeout_s` (remote ones); None keeps theirs. `record_actions`: each
    episode's commanded actions go to `actions_file(output_dir, ...)` (.npy), e.g. for `replay`.

    Finished episodes of `run_id` already in `store` are skipped (episodes that ended in an error
    too, unless `retry_errors`). On SIGINT raises `EvaluationInterrupted` after committing every
    finished episode. Writes `<output_dir>/eval/<run_id>/<policy>/eval_info.json` per policy.
    """
    from twinbench.tasks import get_task

    refuse_in_worker_import("evaluate")
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
    if policy_timeout_s is not None and not (isinstance(policy_timeout_s, int | float)
                                             and 0 < float(policy_timeout_s) <= 86_400):
        raise InputError(f"--policy-timeout {policy_timeout_s}: give seconds per policy call in (0, 86400]")
    specs = [parse_policy_spec(p) for p in policies]
    keys = [(s.name, s.checkpoint) for s in specs]
    if len(set(keys)) != len(keys):
        raise ValueError(f"policies {list(policies)} map to duplicate (policy, checkpoint) labels {keys}; "
                         "give distinct specs or names (NAME=SPEC)")
    env_kwargs = dict(env_kwargs or {})
    if "device" in env_kwargs:  # a device this machine lacks: refused before the run is registered
        from twinbench.physics import check_device

        check_device(env_kwargs["device"], "--env-kwargs device")
    states = episode_set(spec_task.n_grid_states, episodes, int(seed))
    store = store if isinstance(store, ResultsStore) else ResultsStore(store)
    protocol = {"task": task, "episodes": episodes if str(episodes).startswith("grid") else int(episodes),
                "init_states": [i for i, _ in states], "seeds": [s for _, s in states],
                "policies": list(policies), "base_seed": int(seed), "env_kwargs": env_kwargs,
                "env_id": spec_task.env_id, "grid": grid_info(task, env_kwargs), "versions": _versions()}
    if spec_task.task_cls is not None:  # a twin (directory or built-in cell): resuming needs the same one
        protocol["twin_hash"] = _twin_hash(task, env_kwargs, run_id, store)
    known = {(s.name, s.checkpoint) for s in _parsed(_stored_policies(store, run_id))}
    moved = moved_twin_keys(store, run_id, protocol)
    if moved and log is not None:
        log(f"run {run_id!r}: its twin is at {env_kwargs.get('twin')} now (the same files as where the run "
            f"started: {store.run_protocol(run_id)['env_kwargs'].get('twin')}); resuming there")
    added = store.start_run(run_id, task, protocol, grow=("policies", *moved))
    new = [p for p in _parsed(added) if (p.name, p.checkpoint) not in known]
    if new and log is not None:  # a resumed run extended with more policies (other settings unchanged)
        log(f"run {run_id!r}: adding {len(new)} policies to those it was started with")
    out_dir = Path(output_dir)
    jobs: dict[tuple[str, str, int, int], EpisodeJob] = {}  # by (policy, checkpoint, init_state, seed)
    for spec in specs:
        for init_state, s in states:
            video_path = None
            if video:
                folder = out_dir / "videos" / run_id / policy_folder(spec.name, spec.checkpoint)
                video_path = str(folder / f"init{init_state}_seed{s}.mp4")
            actions = (str(actions_file(out_dir, run_id, spec.name, spec.checkpoint, init_state, s))
                       if record_actions else None)
            jobs[(spec.name, spec.checkpoint, init_state, s)] = EpisodeJob(
                task, spec.spec, init_state, s, run_id, env_kwargs, video_path, video_views,
                None if policy_timeout_s is None else float(policy_timeout_s), actions)
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
    if video:
        shown = "every camera side by side" if video_views == ALL_VIEWS else f"cameras {video_views}"
        log(f"videos: {shown}, under {out_dir / 'videos' / run_id}")
    _remove_partial_videos(todo)  # left by a run killed outright (SIGKILL)
    results = {k: existing[k] for k in skip}
    done_count = [len(jobs) - len(todo)]

    with progress_bar(progress) as bar:
        bar_task = bar.add_task(f"eval {run_id}", total=len(jobs), completed=done_count[0])
        # not a terminal (a log file): the bar shows nothing until the end, so lines at most once a minute
        lines = (ProgressLines(log, f"eval {run_id}", len(jobs), done_count[0])
                 if progress and not bar.console.is_terminal else None)

        def on_done(rec: EpisodeRecord) -> None:
            _remove_partial_videos([jobs[(rec.policy, rec.checkpoint, rec.init_state, rec.seed)]])
            store.record_episode(rec)
            results[(rec.policy, rec.checkpoint, rec.init_state, rec.seed)] = rec
            done_count[0] += 1
            bar.advance(bar_task)
            if lines is not None:
                lines.update(done_count[0], counts)

        def counts() -> str:  # the run's successes and errors so far (for a progress line)
            finished = [r for r in results.values() if r.status == "ok"]
            wins, errors = sum(r.success for r in finished), len(results) - len(finished)
            return f"{wins} success{'es' * (wins != 1)}, {errors} error{'s' * (errors != 1)}"

        t0 = time.perf_counter()
        try:
            with sigterm_as_interrupt():
                if backend == "ray":
                    run_ray(batches, int(workers), on_done)
                else:
                    run_local(batches, int(workers), on_done)
        except KeyboardInterrupt as err:
            _remove_partial_videos(todo)  # the episodes in flight: their workers were killed mid-video
            # what the store holds (the signal can land between an episode's record and its count)
            held = sum((r.policy, r.checkpoint, r.init_state, r.seed) in jobs for r in store.episodes(run_id))
            left = len(jobs) - held
            what, exc = ("terminated (SIGTERM)", EvaluationTerminated) if isinstance(err, SigTerm) else (
                "interrupted", EvaluationInterrupted)
            msg = (f"{what}: {held} of {len(jobs)} episodes of run {run_id!r} are in "
                   f"{store.path}; re-run the same command (same --run-id) to resume the remaining {left}")
            raise exc(msg, held, len(jobs)) from None
        finally:
            if todo:
                add_run_seconds_quietly(store, run_id, time.perf_counter() - t0)
    missing = [r for r in results.values() if r.metrics.get("video_error")]
    for r in missing:
        log(f"warning: video missing for {r.policy} init_state {r.init_state} seed {r.seed}: "
            f"{r.metrics['video_error']}")
    records = [results[k] for k in jobs]
    if write_eval_info:
        write_eval_infos(records, out_dir / "eval" / run_id)
    return records
