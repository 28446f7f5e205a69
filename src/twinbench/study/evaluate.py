"""A study's evaluation: every policy on the real workcell (real rollouts) and on each twin variant, through
the evaluation runner and one results store, then per variant Pearson r and MMRV with their intervals,
computed from the store.

Store layout (DIR/results/results.sqlite): run `real-rollouts` (the runner's episodes in REAL/world, their
commanded actions under DIR/results/actions/), copied as domain "real" into run `real` (as `import-real`
stores a robot's outcomes, so `twinbench report --real-run-id real` pairs them), one run `twin-<variant>`
per twin, and one run `replay-<variant>` per twin: the real rollouts' actions replayed open loop in that
twin (domain "replay", next to the real outcome), whose confusion matrix says how often the twin, given
exactly what the robot did, ends as the real episode did. A twin that differs from an earlier one only in
appearance (`no-color` from `full`, `neither` from `no-physics`) takes that twin's replays (copied, the
protocol naming the source): a replay renders no camera. Run `real-again`: the real workcell evaluated a
second time, every episode seed offset by AGAIN_SEED, scored against the first as a twin is (study.json's
`real_again`): the r and MMRV that sampling noise alone leaves at this number of episodes.
"""

from __future__ import annotations

import json
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from twinbench.errors import InputError
from twinbench.evaluation import metrics
from twinbench.evaluation.runner import evaluate, moved_twin_keys
from twinbench.evaluation.store import ResultsStore
from twinbench.study.sizes import SIZES, StudySize, size_name, study_size  # noqa: F401 - re-exported
from twinbench.twin.files import load_twin, twin_physics_hash

REAL_ROLLOUTS, REAL = "real-rollouts", "real"
# the real workcell evaluated again, every episode seed offset by AGAIN_SEED (the real rollouts use 0):
# rates that differ from the first evaluation's only by sampling (policy and sensor noise)
REAL_AGAIN, AGAIN_SEED = "real-again", 1000


def episodes_arg(size: StudySize) -> str:
    return "grid" if size.states is None else "grid:" + ",".join(str(i) for i in size.states)


OBSERVED = "front"  # the camera the study's policies see: the only one rendered (TwinEnv's `cameras`)


def env_kwargs(world: Path, size: StudySize, device: str = "cpu") -> dict:
    out = {"twin": str(world), "cameras": OBSERVED}
    if size.episode_seconds is not None:
        out["episode_seconds"] = float(size.episode_seconds)
    if device != "cpu":  # left out on CPU, so that the runs of studies from before --device resume
        out["device"] = device
    return out


def check_run_devices(store: ResultsStore, run_ids, device: str) -> None:
    """Refuse to resume a study's runs on another device than they began on (InputError naming --device):
    an episode's outcome depends on the device's floating-point order, so one run keeps one device."""
    for run_id in run_ids:
        try:
            began = store.run_protocol(run_id).get("env_kwargs", {}).get("device", "cpu")
        except KeyError:  # not started yet
            continue
        if began != device:
            raise InputError(f"{store.path}: run {run_id!r} was started with --device {began}; resume the "
                             f"study with --device {began} (an episode's outcome depends on the device), or "
                             "start it in a new folder")


def twin_run_id(variant: str) -> str:
    return f"twin-{variant}"


def replay_run_id(variant: str) -> str:
    return f"replay-{variant}"


def user_calibration(evidence: Path) -> Path | None:
    """The evidence's camera calibration file (the user's calibration), None without evidence."""
    index = Path(evidence) / "evidence.json"
    return Path(evidence) / json.loads(index.read_text())["calibration"] if index.is_file() else None


def make_policies(task: str, real_world: Path, out: Path, size: str | StudySize = "small",
                  calibration: Path | None = None, log=print, names=None) -> list[str]:
    """Write the study's perception controllers to OUT (one JSON config each, plus calibration.json) and
    return their policy specs. The object's colours (push-T's T, the rope and its marked end) are calibrated
    on labelled images of `real_world`; the camera model is the front camera of `calibration` (the user's
    calibration file, errors and all, as their perception stack would use it: the same in the real workcell
    and in every twin, whose own cameras `refine-cameras` corrected; None: each env's own camera).
    `names`: a subset of `policies.levels` (None: all)."""
    from twinbench.study import policies as perception

    if task not in perception.LEVELS:
        raise InputError(f"study policies: perception controllers exist for {sorted(perception.LEVELS)}, "
                         f"not {task!r}")
    sz = study_size(size)
    from twinbench.tasks import get_task

    n = get_task(task).n_grid_states
    images = np.linspace(0, n - 1, sz.calibration_images).round().astype(int).tolist()
    t0 = time.perf_counter()
    colors = perception.calibrate_colors({"twin": str(real_world)}, images, OBSERVED, task=task)
    camera = None
    if calibration is not None:
        camera = perception.calibration_camera(calibration, OBSERVED)
    out.mkdir(parents=True, exist_ok=True)
    (out / "calibration.json").write_text(json.dumps(
        {"colors": colors, "images": images, "camera_model": camera, "source": "real workcell, labelled"},
        indent=1))
    log(f"colour calibration on {len(images)} real images: {time.perf_counter() - t0:.1f} s")
    specs = []
    for name, cfg in perception.levels(colors, camera, task).items():
        if names is not None and name not in names:
            continue
        path = perception.write_config(cfg, out / f"{name}.json")
        specs.append(f"{name}=perceive:{path}")
    return specs


def with_user_policies(task: str, study: list[str] | None, user) -> list[str]:
    """The study's policy specs followed by the user's own (`--policy`: any spec `twinbench eval` takes),
    checked before anything runs: each must parse, no two may share a (policy, checkpoint) label, and no
    user policy may take the name of one of the study's (or of the task's perception controllers).
    `study` None checks the user's alone (a `study run` before its policies exist)."""
    from twinbench.policies import parse_policy_spec
    from twinbench.study.policies import LEVELS

    user = list(user or ())
    labels: dict[tuple[str, str], str] = {}
    study_names: set[str] = set()
    for text in [*(study or []), *user]:
        spec = parse_policy_spec(text)
        key = (spec.name, spec.checkpoint)
        if key in labels:
            raise InputError(f"--policy {text!r}: its label (policy {spec.name!r}, checkpoint "
                             f"{spec.checkpoint!r}) is also {labels[key]!r}'s; name it: "
                             f"--policy MINE={_unnamed(text)}")
        if text in user and (spec.name in LEVELS.get(task, {}) or spec.name in study_names):
            raise InputError(f"--policy {text!r}: {spec.name!r} is one of the study's own policies; name "
                             f"yours otherwise: --policy MINE={_unnamed(text)}")
        labels[key] = text
        if text not in user:
            study_names.add(spec.name)
    return [*(study or []), *user]


def _unnamed(text: str) -> str:
    """A policy spec without its NAME= prefix (parse_policy_spec's rule)."""
    head, sep, rest = text.partition("=")
    return rest if sep and ":" not in head and "@" not in head else text


def _real_records(store: ResultsStore, task: str, recs) -> None:
    """Copy the real rollouts' records as domain "real" into run `real` (replacing earlier copies)."""
    ok = [replace(r, run_id=REAL, domain="real") for r in recs if r.status == "ok"]
    protocol = {"kind": "study real rollouts", "task": task, "source_run": REAL_ROLLOUTS,
                "grid": store.run_protocol(REAL_ROLLOUTS).get("grid")}  # for the report's pairing check
    store.start_run_with_episodes(REAL, task, protocol, ok)


def run_evaluations(task: str, real_world: Path, twins: dict[str, Path], policies: list[str], out: Path,
                    size: str | StudySize = "small", workers: int = 1, log=print,
                    retry_errors: bool = False, real_again: bool | None = None,
                    device: str = "cpu", real_only: bool = False) -> dict[str, float]:
    """Every policy on the real workcell (a second time with other episode seeds where `real_again`, by
    default the size's) and on each twin (resumable: the runner skips finished episodes, and those that
    ended in an error unless `retry_errors`), then the real rollouts replayed in each twin, all with
    physics and rendering on Warp device `device` (every run resumes on the device it began on). Returns
    the wall time (s) of each evaluation, over every session that ran some of its episodes. `real_only`:
    the real rollouts alone (no second real evaluation, twins or replays)."""
    from twinbench.physics import check_device

    sz = study_size(size)
    check_device(device, "--device")
    store = ResultsStore(out / "results" / "results.sqlite")
    times = {}
    if real_again is None:
        real_again = sz.real_again
    again = [(REAL_AGAIN, real_world, AGAIN_SEED)] if real_again else []
    runs = [(REAL_ROLLOUTS, real_world, 0), *again, *((twin_run_id(v), p, 0) for v, p in twins.items())]
    if real_only:
        runs, twins = runs[:1], {}
    check_run_devices(store, [r for r, _, _ in runs] + [replay_run_id(v) for v in twins], device)
    for run_id, world, seed in runs:
        t0 = time.perf_counter()
        recs = evaluate(task, policies, episodes=episodes_arg(sz), workers=workers, run_id=run_id,
                        store=store, env_kwargs=env_kwargs(world, sz, device), output_dir=out / "results",
                        log=log, record_actions=run_id == REAL_ROLLOUTS, retry_errors=retry_errors, seed=seed,
                        progress=True)  # a bar in a terminal, else a line a minute (a study runs for hours)
        now = time.perf_counter() - t0
        times[run_id] = _run_seconds(store, run_id, now)
        bad = [r for r in recs if r.status != "ok"]
        total = f" ({times[run_id]:.0f} s over every session)" if times[run_id] > now + 1 else ""
        log(f"{run_id}: {sum(r.success for r in recs)}/{len(recs)} successes, {len(bad)} errors, "
            f"{now:.0f} s{total}")
        if run_id == REAL_ROLLOUTS:
            _real_records(store, task, recs)
    return times | replay_in_twins(task, store, out / "results", twins, sz, log, workers, device)


def replay_in_twins(task: str, store: ResultsStore, results: Path, twins: dict[str, Path], size: StudySize,
                    log=print, workers: int = 1, device: str = "cpu") -> dict[str, float]:
    """`replay_in_twin` for each twin, except that a twin whose physics equals an earlier one's
    (`twin_physics_hash`: it differs only in appearance, as `no-color` from `full`) gets that twin's replays
    copied (`copy_replays`; again when the source gains replays): a replay renders no camera. A replay run
    that was run rather than copied is resumed as it was started. Returns the wall time (s) per replay
    run."""
    physics: dict[str, str] = {}  # twin_physics_hash -> the first variant with that physics
    times = {}
    for variant, world in twins.items():
        t0 = time.perf_counter()
        same = physics.setdefault(twin_physics_hash(load_twin(world)), variant)
        if same == variant or _copied_from(store, replay_run_id(variant)) not in (None, replay_run_id(same)):
            replay_in_twin(task, store, results, variant, world, size, log, workers, device)
        elif len(store.episodes(replay_run_id(variant))) != len(store.episodes(replay_run_id(same))):
            copy_replays(store, same, variant)  # (only when the source holds replays the copy lacks)
            log(f"{replay_run_id(variant)}: the twin differs from {same!r} only in appearance and a replay "
                f"renders no camera: {replay_run_id(same)}'s outcomes, not run again")
        times[replay_run_id(variant)] = _run_seconds(store, replay_run_id(variant), time.perf_counter() - t0)
    return times


def _run_seconds(store: ResultsStore, run_id: str, now: float) -> float:
    """The wall time spent on a run over every session that ran its episodes (the store's record), or for a
    run from before the store kept it (or a copied one), what this call spent."""
    total = store.run_seconds(run_id)
    return now if total is None else total


def _copied_from(store: ResultsStore, run_id: str) -> str | None:
    """The run a replay run was copied from; None for a run not started; "" for one run as it is."""
    try:
        return store.run_protocol(run_id).get("copied_from", "")
    except KeyError:
        return None


def copy_replays(store: ResultsStore, source: str, variant: str) -> None:
    """Store run `replay-<source>`'s records (both domains) as run `replay-<variant>`, its protocol naming
    the source: for a twin whose physics is the source's."""
    src, run_id = replay_run_id(source), replay_run_id(variant)
    recs = [replace(r, run_id=run_id) for r in store.episodes(src)]
    protocol = {**store.run_protocol(src), "copied_from": src,
                "why": "the twins differ only in appearance (twin_physics_hash); replays render no camera"}
    store.start_run_with_episodes(run_id, store.run_task(src), protocol, recs,
                                  grow=("n_episodes", *moved_twin_keys(store, run_id, protocol)))


def replay_in_twin(task: str, store: ResultsStore, results: Path, variant: str, world: Path,
                   size: StudySize, log=print, workers: int = 1, device: str = "cpu") -> None:
    """The real rollouts' recorded actions replayed open loop in twin `variant` (run `replay-<variant>`,
    in `workers` processes); skipped when that run already holds every replay."""
    from twinbench.evaluation.replay import RecordedEpisode, replay_episodes
    from twinbench.evaluation.runner import actions_file

    real = [r for r in store.episodes(REAL_ROLLOUTS) if r.status == "ok"]
    run_id = replay_run_id(variant)
    if len(store.episodes(run_id, domain="replay")) == len(real):
        return
    episodes = []
    for i, r in enumerate(real):
        path = actions_file(results, REAL_ROLLOUTS, r.policy, r.checkpoint, r.init_state, r.seed)
        if not path.is_file():
            raise InputError(f"{path}: the real rollout's actions are missing; re-run the study's evaluation "
                             "from an empty results folder")
        episodes.append(RecordedEpisode(i, r.init_state, np.load(path, allow_pickle=False), r.success,
                                        r.policy, r.checkpoint, train_step=r.train_step, seed=r.seed))
    blind = {**env_kwargs(world, size, device), "cameras": ""}  # open loop: nothing looks at images
    pairs = replay_episodes(task, episodes, store, run_id, env_kwargs=blind, workers=workers)
    agree = sum(rl.success == rep.success for rl, rep in pairs if rep.status == "ok")
    log(f"{run_id}: {len(pairs)} real rollouts replayed, outcomes agree in {agree}")


def _outcomes(store: ResultsStore, run_id: str, domain: str) -> tuple[dict, dict]:
    """The run's successes (0/1, episodes that ran without error) per (policy, checkpoint) and per grid
    state."""
    by_policy: dict = {}
    by_state: dict = {}
    for r in store.episodes(run_id, domain=domain):
        if r.status == "ok":
            by_policy.setdefault((r.policy, r.checkpoint), []).append(int(r.success))
            by_state.setdefault(r.init_state, []).append(int(r.success))
    return by_policy, by_state


def variant_metrics(store: ResultsStore, variant: str) -> dict:
    """Per-policy success rates in the twin `variant` and in the real workcell, Pearson r (Fisher-z
    interval) and MMRV (bootstrap interval) over the policies both have, from the store; the same rates per
    grid state with r over the states ("states"); and the replays' confusion matrix."""
    row = _scored(store, variant, _outcomes(store, twin_run_id(variant), "sim"))
    from twinbench.evaluation.replay import replay_confusion

    c = replay_confusion(store, replay_run_id(variant), by="task")
    c = next(iter(c.values()), None)
    row["replay"] = None if c is None or not c.n else {
        "tp": c.tp, "fp": c.fp, "fn": c.fn, "tn": c.tn, "excluded": c.excluded, "accuracy": c.accuracy}
    return row


def real_again_metrics(store: ResultsStore) -> dict | None:
    """The second real evaluation (`REAL_AGAIN`) against the first, as `variant_metrics` scores a twin (no
    replays); None when the store has none. A twin that matched the real workcell's success rates exactly
    would score about this, given the episodes' sampling noise: at few episodes per policy, r well below 1."""
    again = _outcomes(store, REAL_AGAIN, "sim")
    return _scored(store, "real again", again) if again[0] else None


def _scored(store: ResultsStore, label: str, outcomes: tuple[dict, dict]) -> dict:
    """A run's `_outcomes` against the real rollouts': per policy (`_agreement`) and per grid state."""
    real, real_states = _outcomes(store, REAL, "real")
    row = _agreement(label, outcomes[0], real)
    row["states"] = _state_agreement(outcomes[1], real_states)
    return row


def pearson_entry(sim, real, controls: int = 0) -> dict:
    """`metrics.pearson` as study.json keeps it: r with its interval, or None and why it is undefined."""
    try:
        pr = metrics.pearson(sim=sim, real=real, controls=controls)
        return {"r": pr.r, "low": pr.low, "high": pr.high}
    except ValueError as err:  # fewer than 3 values or a constant vector: r is undefined, said why
        return {"r": None, "low": None, "high": None, "why": str(err)}


def _state_agreement(sim: dict, real: dict) -> dict:
    """Success rate per grid state (over all policies) in the twin and the real workcell, and Pearson r
    over the states: where a twin is wrong, which initial states it gets wrong (a twin can rank the
    policies well and still fail from states where the real workcell succeeds, or the other way round)."""
    keys = sorted(set(sim) & set(real))
    rates = [{"init_state": k, "sim": float(np.mean(sim[k])), "real": float(np.mean(real[k])),
              "n_sim": len(sim[k]), "n_real": len(real[k])} for k in keys]
    return {"rates": rates, "pearson": pearson_entry([d["sim"] for d in rates], [d["real"] for d in rates])}


def _agreement(variant: str, sim: dict, real: dict) -> dict:
    keys = sorted(set(sim) & set(real))
    row: dict = {"variant": variant, "n_policies": len(keys),
                 "n_episodes": {"sim": sum(len(sim[k]) for k in keys),
                                "real": sum(len(real[k]) for k in keys)},
                 "policies": [{"policy": p, "checkpoint": c, "sim": float(np.mean(sim[(p, c)])),
                               "real": float(np.mean(real[(p, c)])), "n_sim": len(sim[(p, c)]),
                               "n_real": len(real[(p, c)])} for p, c in keys]}
    row["pearson"] = pearson_entry([d["sim"] for d in row["policies"]], [d["real"] for d in row["policies"]])
    if keys:
        est = metrics.mmrv_bootstrap(sim=[sim[k] for k in keys], real=[real[k] for k in keys])
        row["mmrv"] = {"value": est.value, "low": est.low, "high": est.high}
    else:
        row["mmrv"] = {"value": None, "low": None, "high": None}
    return row


def study_table(store: ResultsStore, variants) -> list[dict]:
    return [variant_metrics(store, v) for v in variants]


def write_study_json(out: Path, task: str, size: str | StudySize, variants, stages: dict[str, float],
                     extra: dict | None = None) -> dict:
    """DIR/study.json: the table (per variant r with interval, MMRV with interval, n policies, n episodes)
    from the store, the same for a second real evaluation (`real_again`, null without one), the per-stage
    wall times, the study's settings, the real workcell's content hash and what the fits of DIR/twins reached
    (`reconstruct.fit_summary`, `reconstruct.camera_summary`)."""
    from twinbench.study.reconstruct import camera_summary, fit_summary

    store = ResultsStore(out / "results" / "results.sqlite")
    doc = {"task": task, "size": size_name(size),
           "settings": asdict(study_size(size)), "variants": study_table(store, variants),
           "real_again": real_again_metrics(store),
           "stage_seconds": {k: round(v, 1) for k, v in stages.items()}, "sysid": fit_summary(out / "twins"),
           "cameras": camera_summary(out / "twins"), "real_world": real_world_hash(out), **(extra or {})}
    text = json.dumps(doc, indent=1)
    (out / "study.json").write_text(text)
    return json.loads(text)  # as a reader of study.json sees it (lists, not tuples)


def real_world_hash(out: Path) -> str | None:
    """The content hash of the study's real workcell DIR/real/world (None without one): which hidden
    workcell a study was run on, whatever its folder is called (`study combine` refuses one twice)."""
    from twinbench.twin.files import twin_dir_hash

    world = Path(out) / "real" / "world"
    return twin_dir_hash(world) if world.is_dir() else None


def training_records(policies: list[str]) -> list[dict]:
    """Per policy whose checkpoint folder holds a train.json (the study's behaviour-cloned policies): its
    name and checkpoint with the record's architecture, data size, epochs, final training loss and
    training time (study.json's "training"; the page joins them with each checkpoint's success)."""
    from twinbench.policies import parse_policy_spec

    out = []
    for text in policies:
        spec = parse_policy_spec(text)
        path = Path(spec.target) / "train.json" if spec.target else None
        if path is None or not path.is_file():
            continue
        rec = json.loads(path.read_text())
        out.append({"policy": spec.name, "checkpoint": spec.checkpoint, "arch": rec.get("arch", "cnn"),
                    **{k: rec.get(k) for k in ("demos", "frames", "epochs", "loss", "train_seconds")}})
    return out


def table_rows(doc: dict) -> list[dict]:
    """study.json's rows in table order: the twin variants, then the second real evaluation if any."""
    return [*doc["variants"], *([doc["real_again"]] if doc.get("real_again") else [])]


def format_r(p: dict) -> str:
    """A `pearson_entry` as the tables print it: r [low, high], or "undefined"."""
    return "undefined" if p["r"] is None else f"{p['r']:.3f} [{p['low']:.2f}, {p['high']:.2f}]"


def format_table(doc: dict) -> str:
    """The study table as Markdown (the README's form); the second real evaluation, if any, last."""
    from twinbench.evaluation.report import MMRV_RANGE

    lines = [f"| task | variant | Pearson r [95% CI] | MMRV [{MMRV_RANGE}] | policies | "
             "episodes (sim / real) | replay agrees (TP/FP/FN/TN) |", "|---|---|---|---|---|---|---|"]
    for row in table_rows(doc):
        p, m = row["pearson"], row["mmrv"]
        r = format_r(p)
        mm = "-" if m["value"] is None else f"{m['value']:.3f} [{m['low']:.3f}, {m['high']:.3f}]"
        rp = row.get("replay")
        rep = "-" if not rp else (f"{rp['accuracy']:.2f} ({rp['tp']}/{rp['fp']}/{rp['fn']}/{rp['tn']})")
        lines.append(f"| {doc['task']} | {row['variant']} | {r} | {mm} | {row['n_policies']} | "
                     f"{row['n_episodes']['sim']} / {row['n_episodes']['real']} | {rep} |")
    note = no_real_order(doc)
    return "\n".join(lines + ([f"\n{note}"] if note else []))


def no_real_order(doc: dict) -> str | None:
    """The warning for a study whose real success rates are all equal (every policy fails, say), else None:
    there every twin's MMRV is 0 and its r undefined, so the table cannot tell twins apart."""
    rates = {p["real"] for row in doc["variants"] for p in row["policies"] if p["n_real"]}
    if len(rates) != 1:
        return None
    return (f"Every policy's real success rate is {rates.pop():.3f}: with no real order to violate, every "
            "twin's MMRV is 0 and its r undefined here, so this workcell cannot rank twins (the twins' own "
            "rates still show which predict it); `study combine` leaves it out of the mean MMRV.")
