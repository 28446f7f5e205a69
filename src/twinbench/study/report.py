"""The study page (DIR/report.html): the table (Pearson r and MMRV with intervals per variant), a sim-vs-real
scatter per variant, what the fitted twins' system identification reached (tracking errors, the tool
friction's choice), example frame pairs real | twin (the front camera at the first grid state, as each
env renders it, camera response included), stage times; and the evaluation report of each variant
(`evaluation.report.write_report` of run `twin-<variant>` against the real rollouts) linked from it."""

from __future__ import annotations

import base64
import io
from pathlib import Path

import numpy as np

from twinbench.evaluation.report import (
    _CSS,
    MMRV_RANGE,
    MMRV_RANGE_NOTE,
    _e,
    _fig_html,
    _note,
    _table,
    write_report,
)
from twinbench.evaluation.store import ResultsStore


def _num(x, fmt: str = ".3f") -> str:
    return "–" if x is None else format(x, fmt)


def _r_cell(p: dict) -> str:
    """A study.json Pearson entry as a table cell: r [low, high], or why it is undefined."""
    return (_e(p.get("why", "undefined")) if p["r"] is None
            else f"{p['r']:.3f} [{_num(p['low'], '.2f')}, {_num(p['high'], '.2f')}]")


def _table_section(doc: dict) -> str:
    from twinbench.study.evaluate import no_real_order, table_rows

    rows = []
    for row in table_rows(doc):
        p, m = row["pearson"], row["mmrv"]
        r = _r_cell(p)
        mm = "–" if m["value"] is None else f"{m['value']:.3f} [{m['low']:.3f}, {m['high']:.3f}]"
        rp = row.get("replay")
        rep = "–" if not rp else f"{rp['accuracy']:.2f} ({rp['tp']} / {rp['fp']} / {rp['fn']} / {rp['tn']})"
        link = ("" if row is doc.get("real_again")
                else f'<a href="reports/{_e(row["variant"])}.html">report</a>')
        rows.append([_e(row["variant"]), r, mm, str(row["n_policies"]),
                     f"{row['n_episodes']['sim']} / {row['n_episodes']['real']}", rep, link])
    return ("<h2>Sim vs real, per twin variant</h2>" + _table(
        ["variant", "Pearson r [95% CI]", f"MMRV [{MMRV_RANGE}]", "policies", "episodes sim / real",
         "replay agrees (TP / FP / FN / TN)", ""],
        rows) + _note("r: Fisher-z interval over the policies' success rates; MMRV: mean maximum rank "
                      "violation, 0 = the twin ranks the policies as the real workcell does. Replay: the "
                      "real rollouts' actions replayed open loop in the twin; the share whose outcome "
                      "matches the real one, and the confusion matrix (positive = success)."
                      + (" Real again: the real workcell evaluated a second time with other episode seeds "
                         "against the first, what a twin with exactly the real success rates would score "
                         "at this number of episodes." if doc.get("real_again") else ""))
        + _note(MMRV_RANGE_NOTE) + (_note(flat) if (flat := no_real_order(doc)) else ""))


def _states_section(doc: dict) -> str:
    """Success rate per grid state, real and in each twin (and the real workcell again): which initial states
    a twin gets wrong."""
    from twinbench.study.evaluate import table_rows

    rows = [row for row in table_rows(doc) if row.get("states", {}).get("rates")]
    if not rows:
        return ""
    real = {d["init_state"]: d for row in rows for d in row["states"]["rates"]}  # every row's states
    cols = {row["variant"]: {d["init_state"]: d["sim"] for d in row["states"]["rates"]} for row in rows}
    body = [[str(k), f"{real[k]['real']:.2f} ({real[k]['n_real']})",
             *[_num(cols[v].get(k), ".2f") for v in cols]] for k in sorted(real)]
    body.append(["r over the states", "", *[
        _e(row["states"]["pearson"].get("why", "undefined")) if row["states"]["pearson"]["r"] is None
        else f"{row['states']['pearson']['r']:.3f}" for row in rows]])
    return "<h2>Success per grid state</h2>" + _table(
        ["grid state", "real (episodes)", *[_e(v) for v in cols]], body) + _note(
        "Each initial state's success rate over all policies. A twin can rank the policies as the real "
        "workcell does and still succeed from the wrong states (or the other way round).")


def _policies_section(doc: dict) -> str:
    """Each policy's success rate, real and in each twin (and the real workcell again): which policies a
    twin over- or under-rates. The user's own (`--policy`) are marked."""
    from twinbench.policies import parse_policy_spec
    from twinbench.study.evaluate import table_rows

    rows = table_rows(doc)
    if not rows or not rows[0].get("policies"):
        return ""
    yours = set()
    for text in doc.get("user_policies", []):
        try:
            yours.add(parse_policy_spec(text).name)
        except ValueError:
            pass
    keys = sorted({(d["policy"], d["checkpoint"]) for row in rows for d in row["policies"]})
    sim = {row["variant"]: {(d["policy"], d["checkpoint"]): d["sim"] for d in row["policies"]}
           for row in rows}
    real = {(d["policy"], d["checkpoint"]): d for row in rows for d in row["policies"]}
    body = [[_e(p) + (" (yours)" if p in yours else ""), _e(c),
             f"{real[(p, c)]['real']:.2f} ({real[(p, c)]['n_real']})",
             *[_num(sim[v].get((p, c)), ".2f") for v in sim]] for p, c in keys]
    return "<h2>Success per policy</h2>" + _table(
        ["policy", "checkpoint", "real (episodes)", *[_e(v) for v in sim]], body) + _note(
        "Each policy's success rate over the grid states, real and in each twin: the points of the scatter "
        "above.")


def _training_section(doc: dict) -> str:
    """The behaviour-cloned checkpoints: training record and success, real and in each twin."""
    rates = {(d["policy"], d["checkpoint"]): {} for d in doc.get("training", [])}
    for row in doc["variants"]:
        for d in row["policies"]:
            if (d["policy"], d["checkpoint"]) in rates:
                rates[(d["policy"], d["checkpoint"])].update({"real": d["real"], row["variant"]: d["sim"]})
    variants = [row["variant"] for row in doc["variants"]]
    rows = []
    for t in doc.get("training", []):
        r = rates[(t["policy"], t["checkpoint"])]
        rows.append([_e(t["policy"]), _e(t["arch"]), str(t["demos"]), str(t["frames"]), str(t["epochs"]),
                     _num(t["loss"], ".4f"), _num(t["train_seconds"], ".0f"), _num(r.get("real"), ".2f"),
                     *(_num(r.get(v), ".2f") for v in variants)])
    return "<h2>Behaviour-cloned checkpoints</h2>" + _table(
        ["checkpoint", "architecture", "demos", "frames", "epochs", "final training loss", "training s",
         "success real", *(f"success {_e(v)}" for v in variants)], rows)


def _push_values(chosen) -> str:
    """A push fit's chosen values ({name: value}; a study before the joint fit: the tool friction alone)."""
    chosen = chosen if isinstance(chosen, dict) else {"tool_friction": chosen}
    return ", ".join(f"{k.replace('_', ' ')} {v:.3g}" for k, v in chosen.items())


def _input_notes(inputs: dict) -> list[str]:
    """What a fit did to its recording before simulating it (a sysid report's ``inputs``), in words."""
    out = []
    for name, r in inputs.items():
        if name == "particles_below_ground":
            if r["below"]:
                out.append(f"{r['below']} of its {r['of']} particles lay below the ground (the deepest "
                           f"{1e3 * r['deepest']:.2f} mm): raised onto it")
        elif r.get("smoothed"):
            unit = "mrad" if name == "tool_rotation" else "mm"  # from rad or m
            what = {"controls": "the probe's control points", "tool_translation": "the tool's position",
                    "tool_rotation": "the tool's rotation"}.get(name, name)
            out.append(f"{what} measured with {1e3 * r['noise']:.2f} {unit} of noise per axis: smoothed "
                       f"before simulating (moved {1e3 * r['rms_change']:.2f} {unit} rms)")
    return out


def _sysid_section(doc: dict) -> str:
    """What the fitted twins' system identification reached: where the pipeline loses what it measures."""
    rows, notes = [], []

    def mm(x) -> str:
        return _num(None if x is None else 1e3 * x, ".2f")

    for name, r in doc.get("sysid", {}).items():
        a, b = r["initial"], r["final"]
        push = r.get("push") or r.get("tool_friction")  # a study before the joint push fit: the tool's alone
        rows.append([_e(name), f"{mm(a['train_error_m'])} → {mm(b['train_error_m'])}",
                     f"{mm(a['val_error_m'])} → {mm(b['val_error_m'])}", _e(str(r.get("kept"))),
                     "–" if push is None else _e(f"{_push_values(push['chosen'])} ({push['reason']})")])
        notes += [f"{name}: {n}" for n in r.get("notes", [])]
        notes += [f"{name}: {n}" for n in _input_notes(r.get("inputs", {}))]
        notes += [f"{name}: {n}" for n in _layout_notes(r.get("layout"), push)]
        probe = (push or {}).get("probe_errors_m")
        if probe:  # the push moved the object's values: what its probe recording says of them
            a, b = probe["probe_fit"], probe["push_fit"]
            notes.append(f"{name}: the probe recording (one uniform stiffness) at the push's values tracks "
                         f"{mm(b['train_error_m'])} / {mm(b['val_error_m'])} mm (fitted / held-out frames), "
                         f"at the probe fit's {mm(a['train_error_m'])} / {mm(a['val_error_m'])} mm")
    if not rows:
        return ""
    return "<h2>System identification of the fitted twins</h2>" + _table(
        ["object", "tracking error, fitted frames (mm): initial → fit", "held-out frames (mm)", "kept stage",
         "from the push"], rows) + "".join(_note(n) for n in notes) + _note(
        "From each object's recorded motion (the evidence): the no-physics twins keep the initial guess.")


def _layout_notes(layout: dict | None, push: dict | None) -> list[str]:
    """What the reconstruction put into the twin beside the fit (`reconstruct.template_layout`'s record with
    the cell's values kept, the push's measured contact distance), in words; none for a study before them."""
    notes = []
    if layout and layout.get("layout") == "template":
        notes.append(f"laid on the task's template ({layout['particles']} particles, the identified "
                     f"{layout['identified_particles']} replaced), total mass {layout['mass']:.4g}, spring Y "
                     f"{layout['spring_Y']:.4g} (the {layout['spring_Y_from']}'s)")
    kept = (layout or {}).get("cell_values")
    if kept:
        notes.append("the motion constrains none of " + ", ".join(kept) + ": the task cell's "
                     + ", ".join(f"{v:.3g}" for v in kept.values()))
    if push and "contact_distance_m" in push:
        notes.append(f"tool contact distance {1e3 * push['contact_distance_m']:.2f} mm, measured from the "
                     "push")
    return notes


def _camera_section(doc: dict) -> str:
    """What `refine-cameras` corrected: how far the user's calibration was from the real images."""
    rows = [[_e(name), f"{c['rms_before']:.2f} → {c['rms_after']:.2f}", f"{c['shift_px']:.2f}",
             f"{c['rotation_deg']:.3f}", f"{1e3 * c['translation_m']:.2f}",
             "yes" if c["adopted"] else "no (kept as calibrated)"]
            for name, c in doc.get("cameras", {}).items()]
    if not rows:
        return ""
    return "<h2>Camera refinement</h2>" + _table(
        ["camera", "image residual (0-255): calibration → refined", "image shift (px, median)",
         "turned (deg)", "moved (mm)", "adopted"], rows) + _note(
        "Each static camera's calibration corrected on its real image of the scanned workcell: the twins' "
        "cameras. The policies keep the user's calibration, in the real workcell as in every twin.")


def _scatter_section(doc: dict) -> str:
    import matplotlib.pyplot as plt

    from twinbench.study.evaluate import table_rows

    rows = table_rows(doc)
    if not rows:
        return ""
    fig, axes = plt.subplots(1, len(rows), figsize=(3.2 * len(rows), 3.2), squeeze=False)
    for ax, row in zip(axes[0], rows, strict=True):
        sim = [d["sim"] for d in row["policies"]]
        real = [d["real"] for d in row["policies"]]
        ax.plot([0, 1], [0, 1], color="0.7", lw=1)
        ax.scatter(sim, real, s=28)
        for d in row["policies"]:
            ax.annotate(d["policy"].split("-")[0], (d["sim"], d["real"]), fontsize=7, xytext=(3, 3),
                        textcoords="offset points")
        r = row["pearson"]["r"]
        mm = _num(row["mmrv"]["value"], ".2f")
        ax.set_title(f"{row['variant']}  r={_num(r, '.2f')}  MMRV={mm}", fontsize=9)
        ax.set_xlim(-0.05, 1.05)
        ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel("second real evaluation" if row is doc.get("real_again") else "twin success rate")
        ax.set_ylabel("real success rate")
    fig.tight_layout()
    return "<h2>Success rates, twin vs real</h2>" + _fig_html(fig, "sim vs real scatter per variant")


def _png(img: np.ndarray) -> str:
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.asarray(img, np.uint8)).save(buf, format="PNG")
    return f'<img alt="frame" src="data:image/png;base64,{base64.b64encode(buf.getvalue()).decode()}">'


def first_frame(task: str, world: Path, camera: str = "front", init_state: int = 0) -> np.ndarray:
    """The camera image at the first observation of grid state `init_state` in the twin directory `world`."""
    from twinbench.tasks import get_task

    env = get_task(task).make_env(twin=str(world))
    try:
        obs, _ = env.reset(seed=0, options={"init_state": init_state})
        return obs["pixels"][camera]
    finally:
        env.close()


def _frames_section(task: str, real_world: Path, twins: dict[str, Path]) -> str:
    real = first_frame(task, real_world)
    cells = []
    for variant, world in twins.items():
        twin = first_frame(task, world)
        cells.append(f"<figure>{_png(np.concatenate([real, twin], axis=1))}"
                     f"<figcaption>real | {_e(variant)}</figcaption></figure>")
    return "<h2>Frames, real | twin (front camera, grid state 0)</h2>" + "".join(cells)


def write_study_report(out: Path, doc: dict, frames: bool = True,
                       twins: dict[str, Path] | None = None) -> Path:
    """DIR/report.html (the study page) and DIR/reports/<variant>.html (each variant's evaluation report).
    `twins`: the twin directory of each variant (default DIR/twins/<variant>), for the frame pairs."""
    import matplotlib

    from twinbench.study.evaluate import REAL, twin_run_id

    matplotlib.use("Agg")
    out = Path(out)
    store = ResultsStore(out / "results" / "results.sqlite")
    twins = twins or {row["variant"]: out / "twins" / row["variant"] for row in doc["variants"]}
    for variant in twins:
        write_report(store, twin_run_id(variant), out / "reports" / f"{variant}.html", real_run_id=REAL)
    stages = "".join(f"<tr><td>{_e(k)}</td><td>{v:.0f} s</td></tr>" for k, v in doc["stage_seconds"].items())
    body = [f"<h1>twinbench study — {_e(doc['task'])} ({_e(doc['size'])})</h1>",
            _table_section(doc), _scatter_section(doc), _policies_section(doc), _states_section(doc)]
    if doc.get("training"):
        body.append(_training_section(doc))
    body.append(_camera_section(doc))
    body.append(_sysid_section(doc))
    if frames and (out / "real" / "world").is_dir() and all(p.is_dir() for p in twins.values()):
        body.append(_frames_section(doc["task"], out / "real" / "world", twins))
    device = _e(doc.get("device", "cpu"))  # (studies from before --device ran on CPU)
    body.append(f"<h2>Stage wall times (evaluations on {device})</h2><table><tbody>{stages}</tbody></table>")
    if doc.get("beside_reconstruct"):
        body.append(f"<p>{_e(' and '.join(doc['beside_reconstruct']))} ran beside the reconstruction: their "
                    "seconds (the real rollouts' in evaluate's) overlap its.</p>")
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            f"<title>twinbench study — {_e(doc['task'])}</title><link rel=\"icon\" href=\"data:,\">"
            f"<style>{_CSS}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
    path = out / "report.html"
    path.write_text(page, encoding="utf-8")
    return path


def _combined_table(task: dict) -> str:
    rows = []
    for v in task["variants"]:
        p, w, m = v["pooled"], v["within"], v["mmrv"]
        per = "; ".join(f"{_e(str(d['study']))}: {_num(d['r'], '.2f')} / {_num(d['mmrv'])}"
                        for d in v["per_workcell"])
        rows.append([_e(v["variant"]), f"{v['workcells']} ({v['points']})", _r_cell(p), _r_cell(w),
                     f"{m['value']:.3f} [{m['low']:.3f}, {m['high']:.3f}]", per,
                     f"{v['aims_met']} of {v['workcells']}"])
    from twinbench.study.combine import flat_note

    missing = "".join(_note(f"{name}: left out, not in {', '.join(studies)}")
                      for name, studies in task["missing"].items())
    if note := flat_note(task):
        missing += _note(note[0].upper() + note[1:] + ".")
    return _table(["variant", "workcells (points)", "pooled r [95% CI]", "within-workcell r [95% CI]",
                   f"mean MMRV [{MMRV_RANGE}]", "per workcell: r / MMRV", "aims met"], rows) + missing


def _combined_scatter(task: dict) -> str:
    import matplotlib.pyplot as plt

    rows = task["variants"]
    if not rows:
        return ""
    fig, axes = plt.subplots(1, len(rows), figsize=(3.2 * len(rows), 3.4), squeeze=False)
    for ax, row in zip(axes[0], rows, strict=True):
        ax.plot([0, 1], [0, 1], color="0.7", lw=1)
        for k, (w, st) in enumerate(zip(row["per_workcell"], row["points_by_workcell"], strict=True)):
            ax.scatter(st["sim"], st["real"], s=24, color=f"C{k % 10}", label=str(w["study"]))
        ax.set_title(f"{row['variant']}  pooled r={_num(row['pooled']['r'], '.2f')}", fontsize=9)
        ax.set_xlim(-0.05, 1.05)
        ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel("second real evaluation" if row["variant"] == "real again" else "twin success rate")
        ax.set_ylabel("real success rate")
    axes[0][0].legend(fontsize=7, loc="upper left")
    fig.tight_layout()
    return _fig_html(fig, f"{task['task']}: sim vs real per variant, coloured by workcell")


def write_combined_report(path: Path, tasks: list[dict]) -> Path:
    """One page for `study combine`: per task the table and a sim-vs-real scatter per variant, each
    workcell's policies in their own colour."""
    import matplotlib

    from twinbench.study.combine import AIM_MMRV, AIM_R

    matplotlib.use("Agg")
    body = ["<h1>twinbench study — workcells combined</h1>"]
    for t in tasks:
        names = ", ".join(f"{s['study']}" + (f" (seed {s['seed']})" if s.get("seed") is not None else "")
                          for s in t["studies"])
        n = len(t["studies"])
        body += [f"<h2>{_e(t['task'])} ({_e(t['size'])}): {n} workcell{'s' if n > 1 else ''}</h2>",
                 _note(f"Studies: {names}."), _combined_table(t), _combined_scatter(t)]
    body.append(_note(
        "Pooled r: Pearson r over every (workcell, policy) point, Fisher-z interval; it credits a twin for "
        "telling which workcells are hard as well as which policies are better. Within-workcell r: the same "
        "with each workcell's mean rate removed from sim and real (workcell partialled out; the interval "
        "loses a degree of freedom per workcell after the first). Mean MMRV: each workcell's MMRV (policies "
        "ranked against the others of their workcell), averaged over the workcells with a real order; its "
        "re-run range resamples episodes within every workcell, policy and domain (where a second "
        "evaluation would put it if the measured rates were true: it can lie above the value). Aims met: "
        "workcells with r >= "
        f"{AIM_R} and MMRV <= {AIM_MMRV}."))
    page = ("<!DOCTYPE html>\n<html lang=\"en\"><head><meta charset=\"utf-8\">"
            "<title>twinbench study — workcells combined</title><link rel=\"icon\" href=\"data:,\">"
            f"<style>{_CSS}</style></head><body>\n" + "\n".join(body) + "\n</body></html>\n")
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(page, encoding="utf-8")
    return path
