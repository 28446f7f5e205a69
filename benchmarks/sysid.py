"""System identification on a held-out family of synthetic cases, with the fit's DEFAULT options.

The family (`twinbench.construct.sysid_family.family_case`, seeded) varies layout (rope, cloth, block,
irregular), spring radius, stiffness pattern (regions with factors, gradients), contact and damping
values and interaction (lift, drag, drop, poke); none of it is what the defaults were tuned on.
Prints `name value unit` lines per case and the spread:
- validation tracking error (held-out final frames) initial / stage 1 / final, and the noise floor (the
  error of the noise-free truth against the noisy tracks: what a perfect fit scores); beside it the truth's
  own values at 1.5x and 2x its substeps (``step_effect``): where that is over 2x the floor the motion is
  chaotic in the time step (a slip or a contact that another step resolves otherwise) and not even the
  truth's values, simulated at the fit's own stable step, can be asked to track at the floor; the count
  of cases over 2x the floor is printed over all cases and over the others (``step_converged``);
- Spearman rank correlation of the stiffness with the truth, like with like: per fitted region (stage 2
  fits one value per spatial region by default), the fit's value against the truth's geometric mean
  over the same springs (per spring when the fit is per spring); the per-spring figure is printed too
  (comparable between fits with different region counts); a fit that left the stiffness uniform ranks
  0 (its region means differ by float rounding alone, which must not rank), and both are in the JSON
  rows (``fit_regions``, ``truth_regions``: mean log Y per region); beside them the figure over the
  regions the motion constrains (``SysIdResult.region_identifiability``: log-Y standard deviation from the
  tracks' Fisher information under ``REGION_STD``; NaN, left out of the spread, where fewer than 3 regions
  are constrained or their truth is one value);
- ground friction error where the motion slides, restitution error where it hits the ground, how many
  within 0.15, and the same over the cases whose fit calls the value constrained by the motion
  (``SysIdResult.identifiability``: what a user's report says; elsewhere the value is a guess), and the
  same over the cases whose true motion shows the value (``contact_effect``: 0.15 more or less of it
  moves the noise-free motion by >= ``SHOWN_MM``; "slides" alone counts a motion where one particle
  slips once);
- the stage kept (the lowest tracking error on the selection frames), whether the second start ran
  (``FitConfig.attachment_starts``), and the stiffness guess over the truth's geometric mean;
- median and worst of each over the family, and the count of diverged cases.

With ``--json``, each row also holds the fit itself (``fit_params``, its simulation settings ``fit_sim`` and
per-spring ``fit_log_y``: `build_model(data, GlobalParams(**fit_params), SimParams(**fit_sim),
log_y=fit_log_y)`), so a case can be scored again without refitting (e.g. with one value set to the
truth's).

With ``--springs withheld``, the fit gets the family's particles and tracks without their springs and
builds its own by its radius rule, searching the rule as it does on a PhysTwin case (whose
``final_data.pkl`` holds no springs); its springs then differ from the truth's, so the stiffness ranks
per fit region against the mean of the true springs nearest it (rest midpoints) and no per-spring figure
is printed.

With ``--oracle truth|uniform``, instead of fitting: what the tracks support. Per case, the region
stiffness is fitted with the TRUE global parameters (contact, damping, control attachment) by
Levenberg-Marquardt on whole-sequence rollouts (finite-difference Jacobian over the regions, the stage-2
frames, the fit's substep rule), starting from the truth's own region values (``truth``: the nearest
maximum-likelihood regions, a local upper bound; unconstrained regions stay where they start) or from one
value, the truth's median (``uniform``: what a fit with perfect global parameters would reach from an
uninformed start). Printed: the rank correlation over every region and over the regions the motion
constrains at the estimate, and the validation error.

Usage: python benchmarks/sysid.py [--cases 12] [--seed 0] [--first 0] [--jobs 1] [--json rows.json]
       [--springs given|withheld] [--oracle truth|uniform]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict
from pathlib import Path

import numpy as np

SHOWN_MM = 0.5
"""a contact value counts as shown by a case's motion where 0.15 more or less of it moves the noise-free
motion by at least this RMS distance (half the tracks' per-axis noise; `contact_effect`)"""


def _rank(fit, truth) -> float:
    """Spearman correlation; NaN where the truth is one value (nothing to rank), 0 where the fit is (within
    1e-6 in log Y: a uniform fit's region means differ by float32 rounding, which must not rank)."""
    from scipy.stats import spearmanr

    fit, truth = np.asarray(fit, np.float64), np.asarray(truth, np.float64)
    keep = np.isfinite(truth)  # a fit region that no true spring lies nearest to (springs withheld)
    fit, truth = fit[keep], truth[keep]
    if len(truth) < 2 or np.ptp(truth) == 0:
        return float("nan")
    return float(spearmanr(fit, truth).statistic) if np.ptp(fit) > 1e-6 else 0.0


def _truth_by_fit_region(res, truth: dict, particles: np.ndarray, region: np.ndarray) -> list[float]:
    """With the springs withheld the fit has its own springs (its radius rule): each of the truth's springs
    joins the fit region of the nearest fit spring (rest midpoints); per fit region, the truth's mean log
    Y over its springs (NaN where none joins)."""
    from scipy.spatial import cKDTree

    n = res.model.num_object_springs
    sp = res.model.springs_np[:n]
    mid_fit = 0.5 * (res.model.x0_np[sp[:, 0]] + res.model.x0_np[sp[:, 1]])
    tsp = truth["springs"]
    mid_true = 0.5 * (particles[tsp[:, 0]] + particles[tsp[:, 1]])
    label = region[cKDTree(mid_fit).query(mid_true)[1]]
    ly = truth["log_y"][: len(tsp)].astype(np.float64)
    return [float(np.mean(ly[label == r])) if np.any(label == r) else math.nan for r in np.unique(region)]


def run_case(i: int, seed: int, springs: str = "given") -> dict:
    from dataclasses import replace

    from twinbench._runtime import quiet_warp
    from twinbench.construct.sysid_family import contact_effect, family_case, step_effect
    from twinbench.construct.sysid_io import sim_dict
    from twinbench.physics.sysid import FitConfig, identify

    quiet_warp()
    data, truth = family_case(i, seed)
    if springs == "withheld":  # the fit builds its own springs by its radius rule (as from a PhysTwin case)
        data = replace(data, springs=None, rest_lengths=None)
    t0 = time.perf_counter()
    try:
        res = identify(data, FitConfig(progress=False), log=lambda _m: None)
    except Exception as exc:  # a diverged or refused case is a result to report, not a crash
        return {"case": data.name, "error": f"{type(exc).__name__}: {exc}"}
    n = res.model.num_object_springs
    region = res.regions[:n] if res.regions is not None else np.zeros(n, np.int64)
    ids = np.unique(region)
    fit_r = [float(np.mean(res.log_y[:n][region == r], dtype=np.float64)) for r in ids]
    if springs == "withheld":
        truth_r = _truth_by_fit_region(res, truth, data.particles, region)
    else:
        truth_r = [float(np.mean(truth["log_y"][:n][region == r], dtype=np.float64)) for r in ids]
    # the regions whose stiffness the fitted motion constrains (SysIdResult.region_identifiability)
    info = res.region_identifiability.get("regions", [])[: len(ids)] if res.regions is not None else []
    con = [j for j, row in enumerate(info) if row["constrained"]]
    val = list(data.val_frames)
    floor = float(np.mean([np.mean(np.linalg.norm(truth["positions"][k][data.tracked_indices][m]
                                                  - data.tracked[k][m], axis=1))
                           for k in val for m in [data.motion_valid[k]]]))
    out = {"case": data.name, "pattern": truth["pattern"], "seconds": time.perf_counter() - t0,
           "val_initial": res.evals["initial"].val_error, "val_stage1": res.evals["stage1"].val_error,
           "val_final": res.evals["final"].val_error, "floor": floor,
           # the truth's own values at 1.5x and 2x its substeps: over 2x the floor, the motion is chaotic
           "step_floor": step_effect(data, truth),
           "spearman": _rank(fit_r, truth_r) if len(ids) > 2 else float("nan"),
           "regions": len(ids), "constrained": len(con),
           "spearman_constrained": _rank([fit_r[j] for j in con], [truth_r[j] for j in con])
           if len(con) > 2 else float("nan"),
           "spearman_springs": _rank(res.log_y[:n], truth["log_y"][:n]) if springs == "given" else math.nan,
           "springs": springs, "fit_springs": n, "true_springs": len(truth["springs"]),
           "fit_regions": fit_r, "truth_regions": truth_r,
           "slides": truth["slides"], "impacts": truth["impacts"], "notes": res.notes,
           "evaluations": len(res.stage1_history), "epochs": len(res.stage2_history) - 1,
           "kept": res.selection.get("kept", "final"),
           "starts": len(res.selection.get("starts", [])) or 1,  # 2: the second start ran (FitConfig)
           "guess_Y_ratio": (res.guesses.get("spring_Y", {}).get("value") or math.nan)
           / math.exp(float(np.mean(truth["log_y"][:n]))),
           "diverged": any(e.diverged for e in res.evals.values()),
           # the fit itself, to score it again without refitting (e.g. with one value set to the truth's)
           "fit_params": asdict(res.params), "fit_sim": sim_dict(res.sim), "fit_log_y": res.log_y.tolist()}
    for name in ("ground_friction", "ground_restitution"):  # whether the fit calls it constrained
        out[f"{name}_constrained"] = bool(res.identifiability.get(name, {}).get("constrained"))
    effect = contact_effect(data, truth, 0.15)  # how far +-0.15 of each contact value moves the true motion
    for key, acts in (("friction", truth["slides"]), ("restitution", truth["impacts"])):
        error = abs(getattr(res.params, f"ground_{key}") - getattr(truth["params"], f"ground_{key}"))
        out[f"{key}_effect_mm"] = 1e3 * effect[key]
        if acts:
            out[f"{key}_error"] = error
        if out[f"{key}_effect_mm"] >= SHOWN_MM:
            out[f"{key}_error_shown"] = error
    return out


def oracle_case(i: int, seed: int, start: str = "truth", iterations: int = 10) -> dict:
    """Case ``i``'s regions fitted with the true global parameters from ``start`` (module docstring)."""
    from dataclasses import replace

    from twinbench._runtime import quiet_warp
    from twinbench.construct.sysid_family import family_case
    from twinbench.physics import sysid as S
    from twinbench.physics.params import SimParams
    from twinbench.physics.solver import SpringMassSolver

    quiet_warp()
    data, truth = family_case(i, seed)
    t0 = time.perf_counter()
    n = len(truth["springs"])
    log_y = truth["log_y"][:n].astype(np.float64)
    params = replace(truth["params"], spring_Y=float(np.exp(np.median(log_y))))
    hi = float(log_y.max()) + math.log(3.0)  # the LM steps' bounds; substeps stable at the upper one
    lo = float(log_y.min()) - math.log(10.0)
    topo = S.build_model(data, params, SimParams())
    base = S.FitConfig().base_params(data.fps, S.stable_substeps(topo, math.exp(hi), params.dashpot_damping,
                                                                  data.fps))
    model = S.build_model(data, params, base)
    region = S.spring_regions(model, S.AdamConfig().regions)  # the fit's regions (seeded k-means)
    ids = np.unique(region[:n])
    truth_r = np.array([log_y[region[:n] == r].mean() for r in ids])
    x = np.full(int(region.max()) + 1, math.log(params.spring_Y))  # control springs: the median
    if start == "truth":
        x[ids] = truth_r
    frames, solver = S._fitted_frames(data), SpringMassSolver(model)

    def cost(v: np.ndarray) -> float:
        model.set_spring_log_y(v[region].astype(np.float32))
        try:
            xs = S.rollout(model, data.controls, max(frames), solver)[0].astype(np.float64)
        except S.SimulationDiverged:
            return math.inf
        r = S._track_vector(xs, data, frames)
        return float(r @ r)

    lam = 1e-2
    for _ in range(iterations):
        model.set_spring_log_y(x[region].astype(np.float32))
        jac, r0 = S._region_jacobian(model, data, region, frames, 0.05, solver)
        c0, jtj, g = float(r0 @ r0), jac.T @ jac, jac.T @ r0
        damp = np.diag(np.diag(jtj) + 1e-9 * np.trace(jtj) + 1e-30)
        while lam < 1e6:  # Levenberg-Marquardt: a smaller step until the whole rollout improves
            trial = np.clip(x - np.clip(np.linalg.solve(jtj + lam * damp, g), -1.0, 1.0), lo, hi)
            if cost(trial) < c0 * (1.0 - 1e-6):
                x, lam = trial, max(lam / 3.0, 1e-6)
                break
            lam *= 4.0
        else:
            break
    model.set_spring_log_y(x[region].astype(np.float32))
    jac, r0 = S._region_jacobian(model, data, region, frames, 0.05, solver)
    std = S._region_std(jac, max(float(np.mean(r0 * r0)), 1e-12))[ids]
    con = std < S.REGION_STD
    ev = S.evaluate(model, data, S.SequenceLoss(data))
    return {"case": data.name, "start": start, "pattern": truth["pattern"],
            "seconds": time.perf_counter() - t0,
            "val_final": ev.val_error, "constrained": int(con.sum()), "regions": len(ids),
            "spearman": _rank(list(x[ids]), list(truth_r)),
            "spearman_constrained": _rank(list(x[ids][con]), list(truth_r[con])) if con.sum() > 2
            else float("nan")}


def _print_case(r: dict) -> None:
    if "error" in r:
        print(f"sysid_case_{r['case']}_failed 1 count  # {r['error']}", flush=True)
        return
    extra = ""
    for k in ("friction", "restitution"):
        if f"{k}_error" in r:
            loose = "" if r[f"ground_{k}_constrained"] else " (not constrained)"
            extra += f" {k}_error {r[f'{k}_error']:.3f}{loose}"
        extra += f" {k}_effect {r[f'{k}_effect_mm']:.2f} mm"
    print(f"sysid_case_{r['case']} val_mm {1e3 * r['val_initial']:.2f}/{1e3 * r['val_stage1']:.2f}/"
          f"{1e3 * r['val_final']:.2f} floor_mm {1e3 * r['floor']:.2f} "
          f"ratio {r['val_final'] / r['floor']:.2f} (the truth at other steps "
          f"{r['step_floor'] / r['floor']:.2f}) "
          f"spearman {r['spearman']:.3f} ({r['regions']} regions; "
          f"per spring {r['spearman_springs']:.3f}; over the {r['constrained']} constrained regions "
          f"{r['spearman_constrained']:.3f}){extra} "
          f" kept {r['kept']} starts {r['starts']} guess/truth Y {r['guess_Y_ratio']:.2f} "
          f"({r['pattern']}, {r['seconds']:.0f} s)"
          f"{' notes: ' + '; '.join(r['notes']) if r['notes'] else ''}", flush=True)


def _spread(name: str, vals: list[float], unit: str, scale: float = 1.0) -> None:
    vals = [v for v in vals if math.isfinite(v)]
    if not vals:
        return
    worst = min(vals) if name.startswith("spearman") else max(vals)
    print(f"sysid_family_{name}_median {scale * statistics.median(vals):.3f} {unit}")
    print(f"sysid_family_{name}_worst {scale * worst:.3f} {unit}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=12)
    ap.add_argument("--first", type=int, default=0)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--json", default="", help="also write the per-case rows to this JSON file")
    ap.add_argument("--oracle", choices=("truth", "uniform"), default=None,
                    help="fit the regions with the true global parameters instead (module docstring)")
    ap.add_argument("--springs", choices=("given", "withheld"), default="given",
                    help="withheld: the fit gets no springs and builds its own by its radius rule (the "
                    "PhysTwin route); the stiffness ranks per fit region against the true springs nearest it")
    args = ap.parse_args()
    ids = list(range(args.first, args.first + args.cases))
    t0 = time.perf_counter()
    rows = []
    if args.oracle:
        with ProcessPoolExecutor(max_workers=max(args.jobs, 1)) as pool:
            for fut in as_completed([pool.submit(oracle_case, i, args.seed, args.oracle) for i in ids]):
                r = fut.result()
                rows.append(r)
                print(f"sysid_oracle_{args.oracle}_{r['case']} spearman {r['spearman']:.3f} "
                      f"spearman_constrained {r['spearman_constrained']:.3f} "
                      f"({r['constrained']} of {r['regions']} regions constrained) val_mm "
                      f"{1e3 * r['val_final']:.2f} ({r['pattern']}, {r['seconds']:.0f} s)", flush=True)
        _spread(f"spearman_oracle_{args.oracle}", [r["spearman"] for r in rows], "ratio")
        _spread(f"spearman_constrained_oracle_{args.oracle}", [r["spearman_constrained"] for r in rows],
                "ratio")
        print(f"sysid_family_oracle_{args.oracle}_constrained_cases "
              f"{sum(math.isfinite(r['spearman_constrained']) for r in rows)} count")
        print(f"sysid_family_total {time.perf_counter() - t0:.0f} s")
        return
    with ProcessPoolExecutor(max_workers=max(args.jobs, 1)) as pool:
        for fut in as_completed([pool.submit(run_case, i, args.seed, args.springs) for i in ids]):
            rows.append(fut.result())
            _print_case(rows[-1])
    ok = [r for r in rows if "error" not in r]
    print(f"sysid_family_cases {len(rows)} count")
    print(f"sysid_family_failed_or_diverged {len(rows) - len(ok) + sum(r['diverged'] for r in ok)} count")
    _spread("val_error_final", [r["val_final"] for r in ok], "mm", 1e3)
    _spread("val_over_floor", [r["val_final"] / r["floor"] for r in ok], "ratio")
    print(f"sysid_family_over_2x_floor {sum(r['val_final'] > 2 * r['floor'] for r in ok)} count")
    # cases whose motion depends on the time step (step_effect): the truth's own values at another step
    # track over 2x the floor, so a fit (at its own stable step) cannot be asked for less there
    steady = [r for r in ok if r["step_floor"] <= 2 * r["floor"]]
    print(f"sysid_family_step_sensitive {len(ok) - len(steady)} count")
    print(f"sysid_family_over_2x_floor_step_converged {sum(r['val_final'] > 2 * r['floor'] for r in steady)} "
          "count")
    _spread("spearman", [r["spearman"] for r in ok], "ratio")
    _spread("spearman_springs", [r["spearman_springs"] for r in ok], "ratio")
    _spread("spearman_constrained", [r["spearman_constrained"] for r in ok], "ratio")
    ranked = sum(math.isfinite(r["spearman_constrained"]) for r in ok)
    print(f"sysid_family_spearman_constrained_cases {ranked} count")
    for key, where in (("friction", "sliding"), ("restitution", "impact")):
        errs = [r[f"{key}_error"] for r in ok if f"{key}_error" in r]
        print(f"sysid_family_{where}_cases {len(errs)} count")
        _spread(f"{key}_error", errs, "abs")
        print(f"sysid_family_{key}_within_0.15 {sum(e <= 0.15 for e in errs)} count")
        # the cases whose fit calls the value constrained by the motion (SysIdResult.identifiability)
        con = [r[f"{key}_error"] for r in ok if f"{key}_error" in r and r[f"ground_{key}_constrained"]]
        print(f"sysid_family_{where}_cases_constrained {len(con)} count")
        _spread(f"{key}_error_constrained", con, "abs")
        print(f"sysid_family_{key}_within_0.15_constrained {sum(e <= 0.15 for e in con)} count")
        # the cases whose true motion shows the value (0.15 either way moves it by >= SHOWN_MM)
        shown = [r[f"{key}_error_shown"] for r in ok if f"{key}_error_shown" in r]
        print(f"sysid_family_{key}_shown_cases {len(shown)} count")
        _spread(f"{key}_error_shown", shown, "abs")
        print(f"sysid_family_{key}_within_0.15_shown {sum(e <= 0.15 for e in shown)} count")
    _spread("seconds", [r["seconds"] for r in ok], "s")
    kept = [r["kept"] for r in ok]
    print("sysid_family_kept " + ", ".join(f"{k} {kept.count(k)}" for k in sorted(set(kept))) + " count")
    print(f"sysid_family_second_start_run {sum(r['starts'] == 2 for r in ok)} count")
    print(f"sysid_family_total {time.perf_counter() - t0:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(sorted(rows, key=lambda r: r["case"]), indent=1) + "\n")


if __name__ == "__main__":
    main()
