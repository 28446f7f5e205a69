"""`twinbench study make-real | evidence | reconstruct | evaluate | run | combine`: a predictive-validity
study on a hidden "real" workcell (twinbench.study). `run` does every stage into one folder:

    twinbench study run --task push-t --out study_pusht --size small
    twinbench study run --task rope-routing --out study_rope --size small

Tasks: push-t, rope-routing and toy-packing, every stage (each has its perception controllers); another
task goes through make-real, evidence and reconstruct, and `evaluate` / `run` refuse it, naming the tasks
that have them. `--policy NAME=SPEC` adds your own policies to `evaluate` and `run`. `combine` reads
finished studies of one task on other workcells (seeds) as one table:

    twinbench study combine study_s0 study_s1 study_s2 --out combined
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import tyro
from tyro.conf import UseAppendAction

from twinbench.study.reconstruct import VARIANTS


@dataclass(frozen=True)
class MakeRealConfig:
    """Write the hidden real workcell REAL/world (a twin directory) and REAL/hidden.json."""

    out: Path
    """the folder REAL"""
    task: str = "push-t"
    """push-t | rope-routing | toy-packing"""
    seed: int = 0
    size: str = "small"
    """small | medium (the fast cell) | full (the reference cell)"""


@dataclass(frozen=True)
class EvidenceConfig:
    """Write the evidence a user would have of REAL (scan, boxes, calibration, paired images, motion)."""

    real: tyro.conf.Positional[Path]
    """the folder make-real wrote"""
    out: Path
    seed: int = 0
    size: str = "small"


@dataclass(frozen=True)
class ReconstructConfig:
    """Rebuild twins from the evidence with the public CLI (printing each command), one per variant."""

    evidence: tyro.conf.Positional[Path]
    out: Path
    variants: tuple[str, ...] = VARIANTS
    workers: int = 1
    """processes that score each `twinbench sysid` run's candidates (its --cma.workers: the same fit,
    sooner), e.g. the machine's cores"""


@dataclass(frozen=True)
class EvaluateConfig:
    """Calibrate the perception policies on the real workcell, evaluate them on it and on every twin of
    DIR/twins, write DIR/study.json and DIR/report.html (DIR as `study run` lays it out)."""

    out: tyro.conf.Positional[Path]
    """the study folder: DIR/real/world and DIR/twins/<variant> must exist"""
    task: str = "push-t"
    size: str = "small"
    workers: int = 1
    bc: bool = False
    """also train small CNN policies by behaviour cloning on expert demonstrations recorded in the real
    workcell (study.bc; needs the torch extra: pip install 'twinbench[torch]')"""
    bc_act: bool = False
    """--bc and also LeRobot ACT policies trained on the same demonstrations, evaluated as LeRobot
    checkpoints (needs the lerobot extra: pip install 'twinbench[lerobot]')"""
    bc_dp: bool = False
    """--bc and also LeRobot Diffusion Policy policies trained on the same demonstrations (as --bc-act)"""
    device: str = "cpu"
    """Warp device of the evaluations' physics and rendering: cpu | cuda | cuda:N (the twins are built on
    CPU either way); a study's runs resume on the device they began on"""
    retry_errors: bool = False
    """run again the episodes the store holds as errors (e.g. a worker process killed), not only the
    missing ones"""
    real_again: bool = False
    """also evaluate the real workcell a second time with other episode seeds (the yardstick for r and
    MMRV: how well one real evaluation predicts another) at a size that leaves it out (small); medium and
    full always do"""
    policy: Annotated[tuple[str, ...], UseAppendAction] = ()  # repeatable: --policy a --policy b
    """your own policies, evaluated beside the study's on the real workcell and every twin: any spec
    `twinbench eval --policy` takes, e.g. mine=lerobot:DIR?io=FILE; they see what the study's policies
    see: the front camera and the robot state"""


@dataclass(frozen=True)
class RunConfig:
    """Every stage: make-real, evidence, reconstruct, policies, evaluate, report (timed in study.json)."""

    out: Path
    task: str = "push-t"
    """push-t | rope-routing | toy-packing (the tasks with perception controllers)"""
    size: str = "small"
    """small: the fast cell, 2 grid states, 15 s episodes | medium: the same, 8 grid states | full: the
    reference cell, every grid state, the task's episode length"""
    seed: int = 0
    workers: int = 1
    """evaluation worker processes, and the processes that score the reconstruction's `twinbench sysid`
    candidates (--cma.workers)"""
    device: str = "cpu"
    """Warp device of the evaluations' physics and rendering: cpu | cuda | cuda:N (the twins are built on
    CPU either way); a study's runs resume on the device they began on"""
    bc: bool = False
    """also train small CNN policies by behaviour cloning on expert demonstrations recorded in the real
    workcell (study.bc; needs the torch extra: pip install 'twinbench[torch]')"""
    bc_act: bool = False
    """--bc and also LeRobot ACT policies trained on the same demonstrations, evaluated as LeRobot
    checkpoints (needs the lerobot extra: pip install 'twinbench[lerobot]')"""
    bc_dp: bool = False
    """--bc and also LeRobot Diffusion Policy policies trained on the same demonstrations (as --bc-act)"""
    real_again: bool = False
    """also evaluate the real workcell a second time with other episode seeds (the yardstick for r and
    MMRV: how well one real evaluation predicts another) at a size that leaves it out (small); medium and
    full always do"""
    policy: Annotated[tuple[str, ...], UseAppendAction] = ()  # repeatable: --policy a --policy b
    """your own policies, evaluated beside the study's on the real workcell and every twin: any spec
    `twinbench eval --policy` takes, e.g. mine=lerobot:DIR?io=FILE; they see what the study's policies
    see: the front camera and the robot state"""


@dataclass(frozen=True)
class CombineConfig:
    """Finished studies of a task, each on its own hidden workcell (`study run --seed S`), as one table:
    per variant the pooled r over every (workcell, policy), r within workcells, the mean MMRV, each
    workcell's r and MMRV and how many meet the aims (twinbench.study.combine)."""

    studies: tyro.conf.Positional[tuple[Path, ...]]
    """study folders (or their study.json), one size; several tasks give one table per task"""
    out: Path | None = None
    """also write OUT/combined.json (the figures) and OUT/combined.html (the table and a scatter per
    variant, each workcell in its colour)"""


StudyCommand = (
    Annotated[MakeRealConfig, tyro.conf.subcommand("make-real")]
    | Annotated[EvidenceConfig, tyro.conf.subcommand("evidence")]
    | Annotated[ReconstructConfig, tyro.conf.subcommand("reconstruct")]
    | Annotated[EvaluateConfig, tyro.conf.subcommand("evaluate")]
    | Annotated[RunConfig, tyro.conf.subcommand("run")]
    | Annotated[CombineConfig, tyro.conf.subcommand("combine")]
)


def _evaluate(cfg: EvaluateConfig) -> int:
    from twinbench.errors import InputError
    from twinbench.study.evaluate import (
        format_table,
        make_policies,
        run_evaluations,
        training_records,
        user_calibration,
        with_user_policies,
        write_study_json,
    )
    from twinbench.study.report import write_study_report

    real, twins_dir = cfg.out / "real" / "world", cfg.out / "twins"
    twins = {p.name: p for p in sorted(twins_dir.iterdir()) if (p / "twin.json").is_file()} if (
        twins_dir.is_dir()) else {}
    if not real.is_dir() or not twins:
        raise InputError(f"{cfg.out}: needs real/world (study make-real) and twins/<variant> (study "
                         "reconstruct); `twinbench study run` makes them")
    from twinbench.physics import check_device

    check_device(cfg.device, "--device")  # before the calibration and training, as the specs below
    with_user_policies(cfg.task, None, cfg.policy)
    rank = {v: i for i, v in enumerate(VARIANTS)}
    twins = dict(sorted(twins.items(), key=lambda kv: (rank.get(kv[0], len(rank)), kv[0])))
    policies = make_policies(cfg.task, real, cfg.out / "policies", cfg.size,
                             user_calibration(cfg.out / "evidence"))
    if cfg.bc or cfg.bc_act or cfg.bc_dp:
        from twinbench.study.bc import make_bc_policies

        policies += make_bc_policies(cfg.task, real, cfg.out / "policies" / "bc", cfg.size, act=cfg.bc_act,
                                     dp=cfg.bc_dp)
    policies = with_user_policies(cfg.task, policies, cfg.policy)
    times = run_evaluations(cfg.task, real, twins, policies, cfg.out, cfg.size, cfg.workers,
                            retry_errors=cfg.retry_errors, real_again=cfg.real_again or None,
                            device=cfg.device)
    doc = write_study_json(cfg.out, cfg.task, cfg.size, list(twins), times,
                           {"policies": policies, "user_policies": list(cfg.policy),
                            "training": training_records(policies), "device": cfg.device})
    write_study_report(cfg.out, doc)
    print(format_table(doc))
    print(f"wrote {cfg.out / 'study.json'} and {cfg.out / 'report.html'}")
    return 0


def main(cfg) -> int:
    if isinstance(cfg, MakeRealConfig):
        from twinbench.study.real import make_real

        print(f"wrote {make_real(cfg.task, cfg.seed, cfg.out, cfg.size)}")
    elif isinstance(cfg, EvidenceConfig):
        from twinbench.study.evidence import make_evidence

        print(f"wrote {make_evidence(cfg.real, cfg.out, cfg.seed, cfg.size)}")
    elif isinstance(cfg, ReconstructConfig):
        from twinbench.study.reconstruct import reconstruct

        for variant, path in reconstruct(cfg.evidence, cfg.out, cfg.variants, workers=cfg.workers).items():
            print(f"{variant}: {path}")
    elif isinstance(cfg, EvaluateConfig):
        return _evaluate(cfg)
    elif isinstance(cfg, CombineConfig):
        import json

        from twinbench.study.combine import combine_studies, format_combined, load_study
        from twinbench.study.report import write_combined_report

        tasks = combine_studies([load_study(p) for p in cfg.studies])
        print(format_combined(tasks))
        if cfg.out is not None:
            if cfg.out.exists() and not cfg.out.is_dir():
                from twinbench.errors import InputError

                raise InputError(f"--out {cfg.out}: a file; give a folder (it gets combined.json and "
                                 "combined.html)")
            cfg.out.mkdir(parents=True, exist_ok=True)
            (cfg.out / "combined.json").write_text(json.dumps(tasks, indent=1))
            page = write_combined_report(cfg.out / "combined.html", tasks)
            print(f"wrote {cfg.out / 'combined.json'} and {page}")
    else:
        import sys

        from twinbench.evaluation.backends import SigTerm, sigterm_as_interrupt
        from twinbench.evaluation.runner import EvaluationTerminated
        from twinbench.study.evaluate import format_table
        from twinbench.study.run import run_study

        try:  # SIGTERM (a scheduler's stop) takes Ctrl-C's path: the stages stop, what they finished is kept
            with sigterm_as_interrupt():
                doc = run_study(cfg.task, cfg.out, cfg.size, cfg.seed, cfg.workers, bc=cfg.bc,
                                bc_act=cfg.bc_act, bc_dp=cfg.bc_dp, real_again=cfg.real_again or None,
                                policies=cfg.policy, device=cfg.device)
        except (SigTerm, EvaluationTerminated) as err:
            if isinstance(err, EvaluationTerminated):
                print(err.message, file=sys.stderr)  # what the evaluation kept
            print(f"twinbench study: terminated (SIGTERM); the same command started again keeps the finished "
                  f"stages and episodes of {cfg.out}", file=sys.stderr)
            return 143
        print(format_table(doc))
        print("stage wall times: " + ", ".join(f"{k} {v:.0f} s" for k, v in doc["stage_seconds"].items()))
        print(f"wrote {cfg.out / 'study.json'} and {cfg.out / 'report.html'}")
        print(f"other workcells (--seed) read with this one as one table: twinbench study combine {cfg.out} "
              "OTHER_DIR ...")
    return 0
