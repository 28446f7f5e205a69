"""`twinbench study run`: a whole study in one call, each stage timed (DIR/study.json `stage_seconds`).

    DIR/real       the hidden real workcell (study.real.make_real)
    DIR/evidence   what a user has of it (study.evidence.make_evidence)
    DIR/twins/V    the twins rebuilt through the public CLI, one per variant (study.reconstruct)
    DIR/policies   the perception controllers' configs and their colour calibration (study.evaluate), and
                   with `bc` the behaviour-cloning demonstrations and checkpoints in DIR/policies/bc
    DIR/results    the results store of every evaluation (real rollouts and each twin)
    DIR/study.json the table and the stage times;  DIR/report.html the study page
"""

from __future__ import annotations

import time
from pathlib import Path

STAGES = ("make-real", "evidence", "reconstruct", "policies", "bc", "evaluate", "report")


class _Timer:
    def __init__(self, log):
        self.seconds: dict[str, float] = {}
        self.log = log

    def __call__(self, stage: str, fn, *args, **kwargs):
        self.log(f"== {stage}")
        t0 = time.perf_counter()
        out = fn(*args, **kwargs)
        self.seconds[stage] = time.perf_counter() - t0
        self.log(f"== {stage}: {self.seconds[stage]:.0f} s")
        return out


def run_study(task: str, out: Path, size: str = "small", seed: int = 0, workers: int = 1,
              variants: tuple[str, ...] | None = None, log=print, bc: bool = False,
              bc_act: bool = False, bc_dp: bool = False, real_again: bool | None = None) -> dict:
    """Every stage of a study of `task` into `out`; returns study.json's content. `bc`: also the CNN
    behaviour-cloning policies (study.bc; the torch extra); `bc_act` / `bc_dp`: those and LeRobot ACT /
    Diffusion Policy policies trained on the same demonstrations (the lerobot extra). `real_again`: evaluate
    the real workcell a second time (None: as the size says; `small` does not)."""
    from twinbench.evaluation.backends import refuse_in_worker_import
    from twinbench.study.evaluate import (
        make_policies,
        run_evaluations,
        study_size,
        training_records,
        user_calibration,
        write_study_json,
    )
    from twinbench.study.evidence import make_evidence
    from twinbench.study.real import make_real
    from twinbench.study.reconstruct import VARIANTS, reconstruct
    from twinbench.study.report import write_study_report

    refuse_in_worker_import("run_study")
    study_size(size)  # a bad --size is refused before anything runs
    from twinbench.errors import InputError
    from twinbench.study.policies import LEVELS

    if task not in LEVELS:  # ... and a task without perception controllers (before hours of stages)
        raise InputError(f"study run --task {task}: perception controllers exist for {sorted(LEVELS)}; "
                         "`twinbench study make-real / evidence / reconstruct` take any built-in task")
    out = Path(out)
    variants = tuple(variants or VARIANTS)
    timer = _Timer(log)
    real = timer("make-real", make_real, task, seed, out / "real", size)
    evidence = timer("evidence", make_evidence, real, out / "evidence", seed, size)
    twins = timer("reconstruct", reconstruct, evidence, out / "twins", variants, log=log)
    world = real / "world"
    policies = timer("policies", make_policies, task, world, out / "policies", size,
                     user_calibration(evidence), log)
    if bc or bc_act or bc_dp:
        from twinbench.study.bc import make_bc_policies

        policies += timer("bc", make_bc_policies, task, world, out / "policies" / "bc", size, log,
                          act=bc_act, dp=bc_dp)
    eval_times = timer("evaluate", run_evaluations, task, world, twins, policies, out, size, workers, log,
                       real_again=real_again)
    extra = {"evaluation_seconds": eval_times, "policies": policies, "seed": seed,
             "training": training_records(policies)}
    doc = write_study_json(out, task, size, list(twins), timer.seconds, extra)
    timer("report", write_study_report, out, doc)
    return write_study_json(out, task, size, list(twins), timer.seconds, extra)  # with the report's time
