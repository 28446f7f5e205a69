"""`twinbench study run`: a whole study in one call, each stage timed (DIR/study.json `stage_seconds`).

    DIR/real       the hidden real workcell (study.real.make_real)
    DIR/evidence   what a user has of it (study.evidence.make_evidence)
    DIR/twins/V    the twins rebuilt through the public CLI, one per variant (study.reconstruct)
    DIR/policies   the perception controllers' configs and their colour calibration (study.evaluate), and
                   with `bc` the behaviour-cloning demonstrations and checkpoints in DIR/policies/bc
    DIR/results    the results store of every evaluation (real rollouts and each twin)
    DIR/study.json the table and the stage times;  DIR/report.html the study page
    DIR/stages.json the run's arguments and each finished stage's result and time

The policies stage and the real rollouts (the evaluate stage's first run, which then finds them finished)
run on a thread beside the reconstruction, whose fits hold one core for long stretches; study.json's
`beside_reconstruct` says so when they did (the stage times overlap).

Started again with the same arguments (after Ctrl-C or a killed machine), a run keeps the stages it
finished (their results recorded in DIR/stages.json and their files still there) and goes on from the first
one that did not finish; the evaluation resumes by itself (finished episodes are kept). Other arguments
in the same DIR are refused. A study folder moved or copied elsewhere keeps its stages there (the record's
paths are read under the folder's new place).
"""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path

STAGES = ("make-real", "evidence", "reconstruct", "policies", "bc", "evaluate", "report")
KEPT = ("make-real", "evidence", "reconstruct", "policies", "bc")  # stages a run started again keeps


def _paths(value) -> list[Path]:
    """The paths a stage's result names (make-real, evidence: a folder; reconstruct: one per variant)."""
    if isinstance(value, str):
        return [Path(value)]
    if isinstance(value, dict):
        return [Path(v) for v in value.values()]
    return []


class _Timer:
    """Runs the stages, timing each; a stage that `record` (DIR/stages.json) holds as finished by an
    earlier run with the same `args` is kept (its result and seconds from the record)."""

    def __init__(self, log, record: Path, args: dict):
        self._lock = threading.Lock()  # a stage may run beside another (run_study's real rollouts)
        self.seconds: dict[str, float] = {}
        self.log = log
        self.record, self.args = record, args
        self.done: dict = {}
        if record.is_file():
            from twinbench.errors import InputError

            try:
                doc = json.loads(record.read_text())
                before, self.done = doc["args"], dict(doc["done"])
            except (ValueError, KeyError, TypeError) as err:
                raise InputError(f"{record}: not a study run's stage record ({err}); remove it to start the "
                                 "study in this folder again from its first stage") from None
            self.done = _moved(self.done, _recorded_root(doc), str(record.parent.resolve()))
            if before != args:
                changed = sorted(k for k in set(before) | set(args) if before.get(k) != args.get(k))
                raise InputError(f"{record.parent} holds a study run with other arguments ("
                                 + ", ".join(f"{k}: {before.get(k)!r} there, {args.get(k)!r} now"
                                             for k in changed)
                                 + "); give another --out, or remove that folder to start again")

    def __call__(self, stage: str, fn, *args, **kwargs):
        with self._lock:
            kept = self.done.get(stage)
            if kept is not None and all(p.exists() for p in _paths(kept["result"])):
                self.seconds[stage] = float(kept["seconds"])
                self.log(f"== {stage}: finished earlier ({self.seconds[stage]:.0f} s then), kept")
                result = kept["result"]
                return {k: Path(v) for k, v in result.items()} if isinstance(result, dict) else (
                    Path(result) if isinstance(result, str) else result)
            if any(STAGES.index(k) >= STAGES.index(stage) for k in self.done):
                # this stage runs again, so every later one does too: forget them before anything changes
                self.done = {k: v for k, v in self.done.items() if STAGES.index(k) < STAGES.index(stage)}
                self._save()
        self.log(f"== {stage}")
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        with self._lock:
            self.seconds[stage] = time.perf_counter() - t0
            self.log(f"== {stage}: {self.seconds[stage]:.0f} s")
            if stage in KEPT:
                result = {k: str(v) for k, v in out.items()} if isinstance(out, dict) else (
                    str(out) if isinstance(out, Path) else out)
                self.done[stage] = {"result": result, "seconds": self.seconds[stage]}
                self._save()
        return out

    def _save(self) -> None:
        tmp = self.record.with_suffix(".json.partial")
        doc = {"args": self.args, "root": str(self.record.parent.resolve()), "done": self.done}
        tmp.write_text(json.dumps(doc, indent=1) + "\n")
        tmp.replace(self.record)


class _Beside:
    """``fn()`` on a thread beside the main one; ``result()`` waits for it and returns its result or raises
    its error. ``stop()`` (the main thread interrupted or failed) makes its evaluation runs stop as after
    Ctrl-C (`evaluation.backends.stop_requests`: the finished episodes kept, the workers killed) and waits
    for it: a signal reaches the main thread only, and a run left going would hold the process (Python's
    exit waits for the worker processes, which ignore SIGTERM) while it went on to its end."""

    def __init__(self, fn):
        self._out: dict = {}
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, args=(fn,), daemon=True, name="twinbench-beside")
        self._thread.start()

    def _run(self, fn) -> None:
        from twinbench.evaluation.backends import stop_requests

        try:
            with stop_requests(self._stop):
                self._out["value"] = fn()
        except BaseException as err:  # handed to result()
            self._out["error"] = err

    def result(self):
        self._thread.join()
        if "error" in self._out:
            raise self._out["error"]
        return self._out.get("value")

    def stop(self, log) -> None:
        """Stop it and wait; log what its interrupted evaluation kept (its message)."""
        self._stop.set()
        self._thread.join()
        err = self._out.get("error")
        if isinstance(err, KeyboardInterrupt) and str(err):
            log(f"beside the reconstruction: {err}")


def _recorded_root(doc: dict) -> str | None:
    """The study folder a stage record was written in: its `root`, or for a record from before that field,
    the folder holding the make-real stage's result (DIR/real)."""
    if isinstance(doc.get("root"), str):
        return doc["root"]
    real = doc["done"].get("make-real", {}).get("result")
    return str(Path(real).parent) if isinstance(real, str) and Path(real).name == "real" else None


def _moved(value, old: str | None, new: str):
    """`value` (a stage record's results) with every path under the folder `old` moved under `new` (a study
    folder moved or copied elsewhere: its twins, policies and evidence are read from where it is now)."""
    if old is None or old == new:
        return value
    if isinstance(value, dict):
        return {k: _moved(v, old, new) for k, v in value.items()}
    if isinstance(value, list):
        return [_moved(v, old, new) for v in value]
    if isinstance(value, str):
        return new if value == old else value.replace(old.rstrip("/") + "/", new.rstrip("/") + "/")
    return value


def run_study(task: str, out: Path, size: str = "small", seed: int = 0, workers: int = 1,
              variants: tuple[str, ...] | None = None, log=print, bc: bool = False,
              bc_act: bool = False, bc_dp: bool = False, real_again: bool | None = None,
              policies=(), device: str = "cpu") -> dict:
    """Every stage of a study of `task` into `out`; returns study.json's content. `bc`: also the CNN
    behaviour-cloning policies (study.bc; the torch extra); `bc_act` / `bc_dp`: those and LeRobot ACT /
    Diffusion Policy policies trained on the same demonstrations (the lerobot extra). `real_again`: evaluate
    the real workcell a second time (None: as the size says; `small` does not). `policies`: the user's own
    policy specs, evaluated beside the study's (not a stage argument: a run started again may add some).
    `device`: the Warp device of the evaluations (physics and rendering; `cpu`, `cuda`, `cuda:N`); the
    hidden workcell, its evidence and the reconstruction run on CPU whatever it is, so a study's twins are
    the same on every machine."""
    from twinbench.evaluation.backends import refuse_in_worker_import
    from twinbench.study.evaluate import (
        make_policies,
        run_evaluations,
        study_size,
        training_records,
        user_calibration,
        with_user_policies,
        write_study_json,
    )
    from twinbench.study.evidence import make_evidence
    from twinbench.study.real import make_real
    from twinbench.study.reconstruct import VARIANTS, reconstruct
    from twinbench.study.report import write_study_report

    refuse_in_worker_import("run_study")
    study_size(size)  # a bad --size is refused before anything runs
    from twinbench.errors import InputError
    from twinbench.physics import check_device

    check_device(device, "--device")  # ... and a device this machine does not have
    from twinbench.study.policies import LEVELS

    if task not in LEVELS:  # ... and a task without perception controllers (before hours of stages)
        raise InputError(f"study run --task {task}: perception controllers exist for {sorted(LEVELS)}; "
                         "`twinbench study make-real / evidence / reconstruct` take any built-in task")
    user = list(policies)
    with_user_policies(task, None, user)  # a bad spec is refused before hours of stages
    out = Path(out).resolve()  # recorded results are absolute; a moved folder is remapped (_moved)
    variants = tuple(variants or VARIANTS)
    out.mkdir(parents=True, exist_ok=True)
    args = {"task": task, "size": size, "seed": int(seed), "variants": list(variants), "bc": bool(bc),
            "bc_act": bool(bc_act), "bc_dp": bool(bc_dp)}
    timer = _Timer(log, out / "stages.json", args)
    real = timer("make-real", make_real, task, seed, out / "real", size)
    evidence = timer("evidence", make_evidence, real, out / "evidence", seed, size)
    world = real / "world"

    def real_rollouts() -> None:  # the policies and the real rollouts need neither the twins nor their cores
        found = timer("policies", make_policies, task, world, out / "policies", size,
                      user_calibration(evidence), log)
        run_evaluations(task, world, {}, with_user_policies(task, found, user), out, size, workers, log,
                        device=device, real_only=True)

    beside: list[_Beside] = []

    def reconstruct_beside(*a, **kw) -> dict[str, Path]:
        """The reconstruction, with the policies stage and the real rollouts on a thread beside it: much of a
        reconstruction holds one core (sysid's stage 2), and the rollouts are the evaluate stage's first
        run, which later finds them finished (the same episodes, seeds and results as run after it)."""
        beside.append(_Beside(real_rollouts))
        return reconstruct(*a, **kw)

    try:
        twins = timer("reconstruct", reconstruct_beside, evidence, out / "twins", variants, log=log,
                      workers=workers)
    except BaseException:  # Ctrl-C (or an error) in the reconstruction: the real rollouts stop too
        for job in beside:
            job.stop(log)
        raise
    for job in beside:
        job.result()
    policies = timer("policies", make_policies, task, world, out / "policies", size,
                     user_calibration(evidence), log)  # kept when it ran beside the reconstruction
    if bc or bc_act or bc_dp:
        from twinbench.study.bc import make_bc_policies

        policies += timer("bc", make_bc_policies, task, world, out / "policies" / "bc", size, log,
                          act=bc_act, dp=bc_dp)
    policies = with_user_policies(task, policies, user)
    eval_times = timer("evaluate", run_evaluations, task, world, twins, policies, out, size, workers, log,
                       real_again=real_again, device=device)
    timer.seconds["evaluate"] = max(timer.seconds["evaluate"], sum(eval_times.values()))  # all sessions'
    extra = {"evaluation_seconds": eval_times, "policies": policies, "user_policies": user, "seed": seed,
             "beside_reconstruct": ["policies", "real rollouts"] if beside else [],
             "training": training_records(policies), "device": device}
    doc = write_study_json(out, task, size, list(twins), timer.seconds, extra)
    timer("report", write_study_report, out, doc)
    return write_study_json(out, task, size, list(twins), timer.seconds, extra)  # with the report's time
