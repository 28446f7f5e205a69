"""Running episodes: one rollout (`run_episode`), the worlds of a many-world env (`run_worlds`), and the
picklable jobs a worker process or a Ray task runs (`run_job`, `run_batch`) with this process's cache of
envs and policies.

Status: "sim_error" when the env reports or raises a simulation failure (or emits a non-finite state),
"policy_error" when the policy raises, cannot be built, or returns a malformed action. The outcome is
the env's `info["is_success"]` at the episode's last step (the env's success rule, e.g. TwinEnv's
"final" window judgement or "early" termination, is stored in the episode's metrics), and the task's
metrics at the last frame (`final_metrics`: e.g. push-T's `msd` and `coverage`) are stored under
`metrics["final"]`, so a near-miss can be told from a clear success afterwards.

Policies may have, besides `select_action` and `reset`: `warm_up(observation)`, called once per built
policy before its first episode with the observation of that episode's initial state (a remote policy
sends one inference request, e.g. to let the server compile its model; the reply is discarded), and a
`timeout_s` attribute, set from `policy_timeout_s` (`twinbench eval --policy-timeout`).
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from twinbench.errors import InputError, PolicyError
from twinbench.evaluation.store import EpisodeRecord
from twinbench.evaluation.video import ALL_VIEWS, VideoWriter, choose_views, error_text, video_frame
from twinbench.policies.spec import make_policy, parse_policy_spec


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
    final: dict | None = None  # the task's metrics at the last frame (final_metrics of the last info)
    actions: np.ndarray | None = None  # the commanded actions (steps, action dim), in order

    def metrics(self, **extra) -> dict:
        """The EpisodeRecord.metrics of this outcome: `extra`, rewards, success rule, error text."""
        out = {**extra, "sum_reward": self.sum_reward, "max_reward": self.max_reward}
        if self.success_rule:
            out["success_rule"] = self.success_rule
        if self.error:
            out["error"] = self.error
        if self.video_error:
            out["video_error"] = self.video_error
        if self.final:
            out["final"] = self.final
        return out


_BOOKKEEPING = ("is_success", "status", "success_rule", "privileged", "error", "final_info",
                "final_observation", "TimeLimit.truncated", "episode")


def final_metrics(info: dict) -> dict:
    """The task's metrics in a step's `info`, as plain JSON values: numbers, strings and small numeric
    lists (at most 16 values); bookkeeping keys (is_success, status, privileged, ...) left out."""
    out = {}
    for key, value in info.items():
        if key in _BOOKKEEPING or not isinstance(key, str):
            continue
        if isinstance(value, str | bool | np.bool_):
            out[key] = value if isinstance(value, str) else bool(value)
            continue
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            continue
        if arr.size == 0 or arr.size > 16 or not np.all(np.isfinite(arr)):
            continue
        out[key] = float(arr) if arr.ndim == 0 else arr.round(9).tolist()
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
    video_views: str = ALL_VIEWS  # "all" (every camera side by side) or cameras joined by "+"
    policy_timeout_s: float | None = None  # seconds per policy call (policies with a `timeout_s`)
    actions_path: str | None = None  # where the episode's commanded actions go (.npy), for replay
    max_steps: int | None = None  # None: the env's time limit (a replay stops where its actions end)
    reset_options: dict | None = None  # more options for env.reset (a replay's measured object poses)


@dataclass(frozen=True)
class EpisodeBatch:
    """Episode jobs of one policy that one process runs together: one at a time in a TwinEnv when
    `worlds` is 1, else as the worlds of one `worlds`-world TwinVectorEnv (picklable, like EpisodeJob)."""

    jobs: tuple[EpisodeJob, ...]
    worlds: int = 1


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
                 video_path: str | Path | None = None, video_views: str = ALL_VIEWS,
                 reset_options: dict | None = None):
        self.env, self.policy, self.init_state, self.seed = env, policy, int(init_state), int(seed)
        self.reset_options = {"init_state": self.init_state, **(reset_options or {})}
        self.t0, self.started = time.perf_counter(), time.time()
        self.rewards: list[float] = []
        self.actions: list[np.ndarray] = []
        self.video_path = video_path
        self.video = VideoWriter(video_path, env) if video_path is not None else None
        self.views = choose_views(env, video_views) if video_path is not None else None
        self.success, self.status, self.error, self.steps, self.rule = False, "ok", None, 0, None
        self.final: dict | None = None
        self.limit = int(max_steps or getattr(env.unwrapped, "_max_episode_steps", 0) or 0)
        if self.limit <= 0:
            raise ValueError("run_episode: env has no _max_episode_steps; pass max_steps")
        self.ended = False

    def start(self) -> None:
        """Reset the env to this episode's initial state and the policy to its seed."""
        try:
            self.obs, self.info = self.env.reset(seed=self.seed, options=self.reset_options)
            self.final = final_metrics(self.info)
            if self.video is not None:
                self.video.add(video_frame(self.obs, self.env, self.views))
        except Exception as err:  # noqa: BLE001 - any env failure is a sim_error, reported with its text
            self._end("sim_error", f"reset: {error_text(err)}")
            return
        try:
            if hasattr(self.policy, "reseed"):
                self.policy.reseed(self.seed)
            else:
                self.policy.reset()
        except Exception as err:  # noqa: BLE001
            self._end("policy_error", f"reset: {error_text(err)}")

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
            self._end("policy_error", error_text(err))
            return None
        action = action.astype(self.env.action_space.dtype)
        self.actions.append(action)
        return action

    def observe(self, result) -> None:
        """Take the env's step result (obs, reward, terminated, truncated, info) or the error it raised."""
        if isinstance(result, BaseException):
            self._end("sim_error", error_text(result))
            return
        self.obs, reward, terminated, truncated, self.info = result
        self.steps += 1
        self.rewards.append(float(reward))
        env_status = self.info.get("status", "ok")
        if env_status != "ok":  # with the env's reason where it gives one (TwinEnv: what diverged, how)
            why = self.info.get("error")
            self._end("sim_error", f"env status {env_status!r} at step {self.steps}"
                      + (f": {why}" if why else ""))
            return
        if not np.all(np.isfinite(np.asarray(self.obs["agent_pos"], dtype=np.float64))):
            self._end("sim_error", f"non-finite agent_pos at step {self.steps}")
            return
        self.success = bool(self.info.get("is_success", False))  # the final frame's judgement
        self.rule = self.info.get("success_rule", self.rule)
        self.final = final_metrics(self.info)
        if self.video is not None:
            self.video.add(video_frame(self.obs, self.env, self.views))
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
            success_rule=self.rule, video_error=video_error, final=self.final,
            actions=np.array(self.actions).reshape(len(self.actions), *self.env.action_space.shape),
        )

    def abort(self) -> None:
        """Delete the unfinished video of an episode cut short (interrupt)."""
        if self.video is not None:
            self.video.abort()


def run_episode(env, policy, *, init_state: int, seed: int, max_steps: int | None = None,
                video_path: str | Path | None = None, video_views: str = ALL_VIEWS,
                reset_options: dict | None = None) -> EpisodeOutcome:
    """Roll `policy` out in `env` from `init_state` (`reset_options`: more options for `env.reset`, e.g.
    measured object poses); never raises for env or policy failures. An interrupt (KeyboardInterrupt)
    deletes the episode's unfinished video and propagates."""
    r = _Rollout(env, policy, init_state=init_state, seed=seed, max_steps=max_steps, video_path=video_path,
                 video_views=video_views, reset_options=reset_options)
    try:
        r.start()
        while (action := r.action()) is not None:
            try:
                result = env.step(action)
            except Exception as err:  # noqa: BLE001 - any env failure is a sim_error, reported with its text
                result = err
            r.observe(result)
    except BaseException:
        r.abort()
        raise
    return r.outcome()


def run_worlds(vec_env, policies: list, episodes: list[tuple[int, int, str | None]],
               video_views: str = ALL_VIEWS) -> list[EpisodeOutcome]:
    """Roll out `episodes` [(init_state, seed, video_path)] in the worlds of `vec_env` (a TwinVectorEnv),
    world i with `policies[i]`, all worlds in one physics frame per step. Each episode's outcome is the
    one `run_episode` gives in a one-world env (same steps, rewards and judgement, bit for bit on CPU);
    a world whose episode ends waits, held, until every episode has ended. Never raises for env or
    policy failures."""
    if len(episodes) > vec_env.num_envs or len(policies) < len(episodes):
        raise ValueError(f"run_worlds: {len(episodes)} episodes for {vec_env.num_envs} worlds and "
                         f"{len(policies)} policies")
    rollouts = [
        _Rollout(vec_env.envs[i], policies[i], init_state=s, seed=seed, video_path=video,
                 video_views=video_views)
        for i, (s, seed, video) in enumerate(episodes)
    ]
    try:
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
    except BaseException:
        for r in rollouts:
            r.abort()
        raise
    return [r.outcome() for r in rollouts]


def prepare_policy(policy, env, job: EpisodeJob) -> str | None:
    """Before a built policy's first episode: set its `timeout_s` from the job's policy time-out and call
    its `warm_up(observation)` (if it has one) with the observation of the job's initial state. Returns
    the failure's text (the job then ends as a policy_error), else None."""
    if job.policy_timeout_s is not None and hasattr(policy, "timeout_s"):
        policy.timeout_s = float(job.policy_timeout_s)
    warm = getattr(policy, "warm_up", None)
    if not callable(warm):
        return None
    try:
        obs, info = env.reset(seed=job.seed, options={"init_state": job.init_state})
        warm(policy_observation(policy, obs, info))
    except Exception as err:  # noqa: BLE001 - a failed warm-up is the policy's failure, with its reason
        return f"warm-up request before the first episode: {error_text(err)}"
    return None


# ---- worker side: one job or batch at a time, with this process's envs and policies ------------------
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
    if job.video_path is not None:
        choose_views(env, job.video_views)  # an unknown camera stops the run (InputError), before any episode
    pol_key = (job.task, job.policy, job.policy_timeout_s)
    policy, build_error = _CACHE.get(pol_key), None
    if policy is None:
        try:
            policy = make_policy(spec, task, env, seed=job.seed)
        except Exception as err:  # noqa: BLE001 - a policy that cannot be built is a policy_error
            build_error = f"building policy {job.policy!r}: {error_text(err)}"
        else:
            build_error = prepare_policy(policy, env, job)
            if build_error is None:
                _CACHE[pol_key] = policy
            else:
                _close(policy)
                policy = None
    if policy is None:
        out = EpisodeOutcome(False, "policy_error", 0, 0.0, error=build_error, started_at=time.time())
    else:
        out = run_episode(env, policy, init_state=job.init_state, seed=job.seed, max_steps=job.max_steps,
                          video_path=job.video_path, video_views=job.video_views,
                          reset_options=job.reset_options)
    return _record(job, out)


def write_actions(path: str | Path, actions: np.ndarray) -> None:
    """An episode's commanded actions as .npy at `path` (written whole, then renamed: never partial)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".partial")
    with open(tmp, "wb") as f:
        np.save(f, actions, allow_pickle=False)
    tmp.replace(path)


def _record(job: EpisodeJob, out: EpisodeOutcome) -> EpisodeRecord:
    if job.actions_path is not None and out.actions is not None:
        write_actions(job.actions_path, out.actions)
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
    if any(j.max_steps is not None or j.reset_options is not None for j in batch.jobs):
        raise ValueError("max_steps and reset_options are for one-world batches (worlds=1)")
    task = get_task(first.task)
    env_key = (first.task, json.dumps(first.env_kwargs, sort_keys=True), "worlds", batch.worlds)
    if env_key not in _CACHE:
        try:
            _CACHE[env_key] = task.make_vector_env(batch.worlds, **first.env_kwargs)
        except TypeError as err:  # an unknown keyword in --env-kwargs
            raise InputError(f"--env-kwargs {json.dumps(first.env_kwargs)}: the {first.task!r} env does not "
                             f"accept them ({err})") from None
    vec = _CACHE[env_key]
    if first.video_path is not None:
        choose_views(vec.envs[0], first.video_views)  # an unknown camera stops the run (InputError)
    policies = []
    for i, job in enumerate(batch.jobs):
        key = (job.task, job.policy, job.policy_timeout_s, "world", i)
        if key not in _CACHE:
            try:
                policy = make_policy(parse_policy_spec(job.policy), task, vec.envs[i], seed=job.seed)
            except Exception as err:  # noqa: BLE001 - a policy that cannot be built is a policy_error
                error = f"building policy {job.policy!r}: {error_text(err)}"
            else:
                error = prepare_policy(policy, vec.envs[i], job)
                if error is not None:
                    _close(policy)
            if error is not None:
                return [_record(j, EpisodeOutcome(False, "policy_error", 0, 0.0, error=error,
                                                  started_at=time.time())) for j in batch.jobs]
            _CACHE[key] = policy
        policies.append(_CACHE[key])
    outs = run_worlds(vec, policies, [(j.init_state, j.seed, j.video_path) for j in batch.jobs],
                      video_views=first.video_views)
    return [_record(j, out) for j, out in zip(batch.jobs, outs, strict=True)]


def close_cached_policies() -> None:
    """Close and forget this process's cached policies (a remote policy's connection is closed here, not
    from `__del__` at interpreter shutdown, where closing it could hang). Cached envs are kept."""
    for key in [k for k, v in _CACHE.items() if hasattr(v, "select_action")]:
        _close(_CACHE.pop(key))


def _close(policy) -> None:
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
