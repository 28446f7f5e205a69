"""Several finished studies of one task, each on its own hidden workcell, read as one
(`twinbench study combine DIR [DIR ...]`).

One study's r rests on its 8 policies (medium), so its interval is wide and its value hangs on that
workcell. Over W workcells, per variant:

- pooled r: Pearson r over every (workcell, policy) point. It credits a twin for telling which workcells
  are hard as well as which policies are better;
- within-workcell r: the same points with each workcell's mean rate taken out of both sim and real (a
  partial correlation, workcell partialled out: the interval loses W - 1 degrees of freedom): how well the
  twins rank policies inside their workcell;
- mean MMRV: the mean of the workcells' MMRVs (a policy is ranked only against the others of its
  workcell), its interval by resampling episodes within every workcell, policy and domain. A workcell
  whose real rates are all equal (every policy fails there, say) is left out of it and named: its MMRV is
  0 whatever the twin does (there is no real order to violate), which would flatter the mean;
- each workcell's r and MMRV, and in how many both aims hold (r >= AIM_R, MMRV <= AIM_MMRV).

Everything is read from each study's study.json (per policy: the rates and episode counts in the twin and
in the real workcell; which hidden workcell it ran on), so combining studies copied from other machines
needs nothing else. One workcell given twice (a copied study) is refused.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from twinbench.errors import InputError
from twinbench.evaluation import metrics
from twinbench.study.evaluate import format_r, pearson_entry, real_world_hash

AIM_R, AIM_MMRV = 0.95, 0.05  # the predictive-validity aims (README, results table)
REAL_AGAIN_LABEL = "real again"


def load_study(path: Path) -> tuple[str, dict]:
    """(the study's name, its study.json) for a study folder or its study.json."""
    path = Path(path)
    file = path / "study.json" if path.is_dir() else path
    if not file.is_file():
        raise InputError(f"{path}: no study.json; give a folder that `twinbench study run` or `study "
                         "evaluate` finished (they write DIR/study.json)")
    try:
        doc = json.loads(file.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise InputError(f"{file}: not readable as JSON ({err}); re-run `twinbench study evaluate` on its "
                         "folder to write it again") from err
    if not isinstance(doc, dict) or not {"task", "size", "variants"} <= set(doc):
        raise InputError(f"{file}: not a study.json (needs task, size and variants); re-run `twinbench "
                         "study evaluate` on its folder")
    if doc.get("real_world") is None:  # written before study.json recorded it: read it off the folder
        doc["real_world"] = real_world_hash(file.parent)
    return file.parent.name, doc


def _same_workcell(group: list[tuple[str, dict]]) -> None:
    """Refuse one hidden workcell twice (a copied study): its policies would count twice."""
    seen: dict = {}
    for name, doc in group:
        key = doc.get("real_world") or (doc.get("seed") is not None and ("seed", doc["seed"])) or name
        if key in seen:
            raise InputError(f"{seen[key]} and {name} are studies of the same hidden workcell (the same "
                             f"{'real/world' if doc.get('real_world') else 'seed'}): give each workcell "
                             "once (to add policies or twins to a study, `study evaluate` it again)")
        seen[key] = name


def _outcomes(rate: float, n: int) -> list[int]:
    """n episode outcomes with the recorded rate (study.json keeps rates and counts, not episodes)."""
    k = int(round(rate * n))
    return [1] * k + [0] * (n - k)


def _rows(doc: dict) -> dict[str, dict]:
    """The study's rows by label, those with at least one policy evaluated in both domains."""
    rows = {row["variant"]: row for row in doc["variants"]}
    if doc.get("real_again"):
        rows[REAL_AGAIN_LABEL] = doc["real_again"]
    return {k: row for k, row in rows.items() if any(p["n_sim"] and p["n_real"] for p in row["policies"])}


def combine_variant(label: str, studies: list[tuple[str, dict, dict]]) -> dict:
    """One variant over the workcells: `studies` = [(name, study.json, its row for `label`)]."""
    sim, real, group, groups, per = [], [], [], [], []
    for g, (name, doc, row) in enumerate(studies):
        pols = [p for p in row["policies"] if p["n_sim"] and p["n_real"]]
        sim += [p["sim"] for p in pols]
        real += [p["real"] for p in pols]
        group += [g] * len(pols)
        groups.append(([_outcomes(p["sim"], p["n_sim"]) for p in pols],
                       [_outcomes(p["real"], p["n_real"]) for p in pols]))
        r, m = row["pearson"]["r"], row["mmrv"]["value"]
        sims, reals = groups[-1]
        per.append({"study": name, "seed": doc.get("seed"), "policies": len(pols), "r": r, "mmrv": m,
                    "sim_successes": sum(map(sum, sims)), "real_successes": sum(map(sum, reals)),
                    "aims_met": r is not None and m is not None and r >= AIM_R and m <= AIM_MMRV})
    s, r, grp = np.asarray(sim), np.asarray(real), np.asarray(group)
    means = {g: (s[grp == g].mean(), r[grp == g].mean()) for g in set(group)}
    s_in = s - np.array([means[g][0] for g in group])
    r_in = r - np.array([means[g][1] for g in group])
    flat = [g for g in range(len(studies)) if np.ptp(r[grp == g]) == 0]  # no real order: MMRV 0 by definition
    ranked = [groups[g] for g in range(len(studies)) if g not in flat]
    est = metrics.mean_mmrv_bootstrap(ranked or groups)
    return {"variant": label, "workcells": len(studies), "points": int(s.size),
            "pooled": pearson_entry(s, r), "within": pearson_entry(s_in, r_in, controls=len(studies) - 1),
            "mmrv": {"value": est.value, "low": est.low, "high": est.high, "workcells": len(ranked or groups),
                     "left_out": [per[g]["study"] for g in flat] if ranked else []},
            "aims_met": sum(p["aims_met"] for p in per), "per_workcell": per,
            "points_by_workcell": [{"sim": s[grp == g].tolist(), "real": r[grp == g].tolist()}
                                   for g in range(len(studies))]}


def combine_studies(studies: list[tuple[str, dict]]) -> list[dict]:
    """Per task (in the order first given): its studies, and per variant (and the second real evaluation)
    that every one of them has, `combine_variant`; variants some lack are listed in `missing`."""
    if not studies:
        raise InputError("no studies given: name the study folders to combine "
                         "(`twinbench study combine A B`)")
    by_task: dict[str, list[tuple[str, dict]]] = {}
    for name, doc in studies:
        by_task.setdefault(doc["task"], []).append((name, doc))
    out = []
    for task, group in by_task.items():
        _same_workcell(group)
        sizes = sorted({doc["size"] for _, doc in group})
        if len(sizes) > 1:
            raise InputError(f"{task}: studies of sizes {sizes} ("
                             + ", ".join(f"{n}: {d['size']}" for n, d in group)
                             + "); combine studies of one size (their grid states and episodes differ)")
        rows = [(name, doc, _rows(doc)) for name, doc in group]
        labels = [v for v in rows[0][2] if all(v in r for _, _, r in rows)]
        missing = {v: [n for n, _, r in rows if v not in r]
                   for v in dict.fromkeys(v for _, _, r in rows for v in r) if v not in labels}
        out.append({"task": task, "size": sizes[0],
                    "studies": [{"study": n, "seed": d.get("seed")} for n, d in group],
                    "variants": [combine_variant(v, [(n, d, r[v]) for n, d, r in rows]) for v in labels],
                    "missing": missing})
    return out


def format_combined(tasks: list[dict]) -> str:
    """The combined table as Markdown, one row per task and variant."""
    from twinbench.evaluation.report import MMRV_RANGE

    lines = ["| task | variant | workcells (points) | pooled r [95% CI] | within-workcell r [95% CI] | "
             f"mean MMRV [{MMRV_RANGE}] | per workcell r / MMRV | aims met |", "|---" * 8 + "|"]
    for t in tasks:
        for v in t["variants"]:
            m = v["mmrv"]
            per = "; ".join(("-" if p["r"] is None else f"{p['r']:.2f}") + f" / {p['mmrv']:.3f}"
                            for p in v["per_workcell"])
            lines.append(f"| {t['task']} | {v['variant']} | {v['workcells']} ({v['points']}) | "
                         f"{format_r(v['pooled'])} | {format_r(v['within'])} | {m['value']:.3f} "
                         f"[{m['low']:.3f}, {m['high']:.3f}] | {per} | {v['aims_met']} of {v['workcells']} |")
    notes = [f"{t['task']}: {v} left out (not in {', '.join(names)})"
             for t in tasks for v, names in t["missing"].items()]
    notes += [f"{t['task']}: {note}" for t in tasks if (note := flat_note(t))]
    return "\n".join(lines + ([""] + notes if notes else []))


def flat_note(task: dict) -> str | None:
    """What the mean MMRV left out of a task's combination: the workcells whose real rates are all equal."""
    names = sorted({n for v in task["variants"] for n in v["mmrv"].get("left_out", [])})
    if not names:
        return None
    return (f"mean MMRV over the other workcells: in {', '.join(names)} every real success rate is the same, "
            "so its MMRV is 0 whatever the twin does (no real order to violate) and its r undefined; its "
            "points stay in the pooled and within-workcell r")
