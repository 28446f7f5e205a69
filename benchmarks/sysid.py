"""System identification on a held-out family of synthetic cases, with the fit's DEFAULT options.

The family (`twinbench.construct.sysid_family.family_case`, seeded) varies layout (rope, cloth, block,
irregular), spring radius, stiffness pattern (regions with factors, gradients), contact and damping
values and interaction (lift, drag, drop, poke); none of it is what the defaults were tuned on.
Prints `name value unit` lines per case and the spread:
- validation tracking error (held-out final frames) initial / stage 1 / final, and the noise floor (the
  error of the noise-free truth against the noisy tracks: what a perfect fit scores);
- Spearman rank correlation of the stiffness with the truth, like with like: per fitted region (stage 2
  fits one value per spatial region by default), the fit's value against the truth's geometric mean
  over the same springs (per spring when the fit is per spring); the per-spring figure is printed too,
  and beside them the figure over the regions the motion constrains (``SysIdResult.
  region_identifiability``: log-Y standard deviation from the tracks' Fisher information under
  ``REGION_STD``; NaN, left out of the spread, where fewer than 3 regions are constrained or their truth
  is one value);
- ground friction error where the motion slides, restitution error where it hits the ground;
- the stage kept (the lowest tracking error on the selection frames) and the stiffness guess over the
  truth's geometric mean;
- median and worst of each over the family, and the count of diverged cases.

Usage: python benchmarks/sysid.py [--cases 12] [--seed 0] [--first 0] [--jobs 1] [--json rows.json]
"""

from __future__ import annotations

import argparse
import json
import math
import statistics
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np


def _rank(fit: list[float], truth: list[float]) -> float:
    """Spearman correlation; NaN where the truth is one value (nothing to rank), 0 where the fit is."""
    from scipy.stats import spearmanr

    if np.ptp(truth) == 0:
        return float("nan")
    return float(spearmanr(fit, truth).statistic) if np.ptp(fit) > 0 else 0.0


def run_case(i: int, seed: int) -> dict:
    from scipy.stats import spearmanr

    from twinbench._runtime import quiet_warp
    from twinbench.construct.sysid_family import family_case
    from twinbench.physics.sysid import FitConfig, identify

    quiet_warp()
    data, truth = family_case(i, seed)
    t0 = time.perf_counter()
    try:
        res = identify(data, FitConfig(progress=False), log=lambda _m: None)
    except Exception as exc:  # a diverged or refused case is a result to report, not a crash
        return {"case": data.name, "error": f"{type(exc).__name__}: {exc}"}
    n = res.model.num_object_springs
    region = res.regions[:n] if res.regions is not None else np.zeros(n, np.int64)
    ids = np.unique(region)
    fit_r = [float(np.mean(res.log_y[:n][region == r])) for r in ids]
    truth_r = [float(np.mean(truth["log_y"][:n][region == r])) for r in ids]
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
           "spearman": float(spearmanr(fit_r, truth_r).statistic) if len(ids) > 2 else float("nan"),
           "regions": len(ids), "constrained": len(con),
           "spearman_constrained": _rank([fit_r[j] for j in con], [truth_r[j] for j in con])
           if len(con) > 2 else float("nan"),
           "spearman_springs": float(spearmanr(res.log_y[:n], truth["log_y"][:n]).statistic),
           "slides": truth["slides"], "impacts": truth["impacts"], "notes": res.notes,
           "evaluations": len(res.stage1_history), "epochs": len(res.stage2_history) - 1,
           "kept": res.selection.get("kept", "final"),
           "guess_Y_ratio": (res.guesses.get("spring_Y", {}).get("value") or math.nan)
           / math.exp(float(np.mean(truth["log_y"][:n]))),
           "diverged": any(e.diverged for e in res.evals.values())}
    if truth["slides"]:
        out["friction_error"] = abs(res.params.ground_friction - truth["params"].ground_friction)
    if truth["impacts"]:
        out["restitution_error"] = abs(res.params.ground_restitution - truth["params"].ground_restitution)
    return out


def _print_case(r: dict) -> None:
    if "error" in r:
        print(f"sysid_case_{r['case']}_failed 1 count  # {r['error']}", flush=True)
        return
    extra = "".join(f" {k} {r[k]:.3f}" for k in ("friction_error", "restitution_error") if k in r)
    print(f"sysid_case_{r['case']} val_mm {1e3 * r['val_initial']:.2f}/{1e3 * r['val_stage1']:.2f}/"
          f"{1e3 * r['val_final']:.2f} floor_mm {1e3 * r['floor']:.2f} "
          f"ratio {r['val_final'] / r['floor']:.2f} spearman {r['spearman']:.3f} ({r['regions']} regions; "
          f"per spring {r['spearman_springs']:.3f}; over the {r['constrained']} constrained regions "
          f"{r['spearman_constrained']:.3f}){extra} "
          f" kept {r['kept']} guess/truth Y {r['guess_Y_ratio']:.2f} ({r['pattern']}, {r['seconds']:.0f} s)"
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
    args = ap.parse_args()
    ids = list(range(args.first, args.first + args.cases))
    t0 = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(max_workers=max(args.jobs, 1)) as pool:
        for fut in as_completed([pool.submit(run_case, i, args.seed) for i in ids]):
            rows.append(fut.result())
            _print_case(rows[-1])
    ok = [r for r in rows if "error" not in r]
    print(f"sysid_family_cases {len(rows)} count")
    print(f"sysid_family_failed_or_diverged {len(rows) - len(ok) + sum(r['diverged'] for r in ok)} count")
    _spread("val_error_final", [r["val_final"] for r in ok], "mm", 1e3)
    _spread("val_over_floor", [r["val_final"] / r["floor"] for r in ok], "ratio")
    _spread("spearman", [r["spearman"] for r in ok], "ratio")
    _spread("spearman_springs", [r["spearman_springs"] for r in ok], "ratio")
    _spread("spearman_constrained", [r["spearman_constrained"] for r in ok], "ratio")
    ranked = sum(math.isfinite(r["spearman_constrained"]) for r in ok)
    print(f"sysid_family_spearman_constrained_cases {ranked} count")
    fr = [r["friction_error"] for r in ok if "friction_error" in r]
    re = [r["restitution_error"] for r in ok if "restitution_error" in r]
    print(f"sysid_family_sliding_cases {len(fr)} count")
    _spread("friction_error", fr, "abs")
    print(f"sysid_family_impact_cases {len(re)} count")
    _spread("restitution_error", re, "abs")
    _spread("seconds", [r["seconds"] for r in ok], "s")
    kept = [r["kept"] for r in ok]
    print("sysid_family_kept " + ", ".join(f"{k} {kept.count(k)}" for k in sorted(set(kept))) + " count")
    print(f"sysid_family_total {time.perf_counter() - t0:.0f} s")
    if args.json:
        Path(args.json).write_text(json.dumps(sorted(rows, key=lambda r: r["case"]), indent=1) + "\n")


if __name__ == "__main__":
    main()
