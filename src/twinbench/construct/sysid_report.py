"""System identification's fit report: ``sysid_report.json`` (figures, histories, settings, the starting
guesses from the data, which stage was kept and why) and ``sysid_report.png`` (loss curves, per-frame
tracking error, stiffness histogram)."""

from __future__ import annotations

import json
import math
import textwrap
from dataclasses import asdict
from pathlib import Path

import numpy as np

from twinbench.construct.sysid_io import sim_dict
from twinbench.physics.sysid import DEFAULT_RANGES, SysIdResult, parse_ranges
from twinbench.physics.sysid_data import SysIdData


def _finite(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def report_dict(result: SysIdResult, data: SysIdData) -> dict:
    """The fit report as JSON-ready data."""
    ys = result.object_spring_Y
    cfg = result.config
    return {
        "name": data.name,
        "frames": {"total": data.num_frames, "train": [data.train_frames.start, data.train_frames.stop - 1],
                   "validation": data.validation_frames},
        "stages": {"stage1": bool(cfg and cfg.stage1), "stage2": bool(cfg and cfg.stage2),
                   "stage3": bool(result.stage3_history), "stage4": bool(result.stage4_history)},
        "global_params": asdict(result.params),
        "sim": sim_dict(result.sim),
        "spring_Y": {"count": int(ys.size), "min": _finite(ys.min()) if ys.size else None,
                     "median": _finite(np.median(ys)) if ys.size else None,
                     "max": _finite(ys.max()) if ys.size else None},
        "evaluations": {name: {"train_loss": _finite(e.train_loss), "train_error_m": _finite(e.train_error),
                               "val_error_m": _finite(e.val_error), "diverged": e.diverged,
                               "per_frame_error_m": [_finite(v) for v in e.track_error],
                               "per_frame_loss": [_finite(v) for v in e.loss]}
                        for name, e in result.evals.items()},
        **{f"stage{k}_history": [{name: _finite(v) if isinstance(v, float) else v for name, v in row.items()}
                                 for row in h]
           for k, h in enumerate((result.stage1_history, result.stage2_history, result.stage3_history,
                                  result.stage4_history), start=1)},
        "stiffness_fit": _stiffness_fit(result),
        "region_identifiability": _jsonable(result.region_identifiability),
        "guesses": _jsonable(result.guesses),
        "inputs": _jsonable(result.inputs),
        "selection": _jsonable(result.selection),
        "notes": list(result.notes),
        "identifiability": {k: {kk: (_finite(vv) if isinstance(vv, float) else vv) for kk, vv in v.items()}
                            for k, v in result.identifiability.items()},
        "seconds": result.seconds,
        "config": _jsonable(asdict(cfg)) if cfg else None,
    }


def _stiffness_fit(result: SysIdResult) -> dict:
    """How stage 2 fitted the stiffness: one global value, per spring, or per spatial region (then each
    object region's spring count and stiffness)."""
    n = result.model.num_object_springs
    if result.regions is None:
        return {"per": "object"}
    reg = result.regions[:n]
    if np.unique(reg).size == n:
        return {"per": "spring", "count": n}
    ys = result.object_spring_Y
    ids = np.unique(reg)
    return {"per": "region", "count": int(ids.size), "springs": [int(np.sum(reg == r)) for r in ids],
            "spring_Y": [_finite(np.exp(np.mean(np.log(ys[reg == r])))) for r in ids]}


def _jsonable(obj):
    if isinstance(obj, dict):
        return {k: _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if isinstance(obj, float):
        return _finite(obj)
    return obj


def _identifiability_panel(a, result: SysIdResult) -> None:
    """Per searched parameter: the interval of stage-1 candidates within 50 % of the best loss, as a
    fraction of its search range (green: constrained by the motion, grey: not; a red diamond: the
    measured value kept in place of the search's point)."""
    ident = result.identifiability
    if not ident:
        a.text(0.5, 0.5, "stage 1 off", ha="center", va="center", transform=a.transAxes)
        return
    ranges = parse_ranges(result.config.cma.ranges) if result.config else DEFAULT_RANGES
    for i, (name, v) in enumerate(ident.items()):
        r = ranges[name]
        lo, hi, best = r.encode(v["low"]), r.encode(v["high"]), r.encode(v["best"])
        a.barh(i, max(hi - lo, 0.005), left=lo, color="C2" if v["constrained"] else "0.7")
        a.plot([best], [i], "k|", ms=12)
        text = f"{v['best']:.3g} [{v['low']:.3g}, {v['high']:.3g}]"
        if v.get("guess_kept"):  # the measured value replaced the search's point (keep_unconstrained_guesses)
            kept = getattr(result.params, name)
            a.plot([r.encode(kept)], [i], "rD", ms=5)
            text += f", kept measured {kept:.3g}"
        a.text(1.01, i, text, va="center", fontsize=8)
    a.set_yticks(range(len(ident)), list(ident))
    a.set_xlim(0.0, 1.0)
    a.set(title="identifiability: loss within 50 % of best", xlabel="position in search range")


def write_report(result: SysIdResult, data: SysIdData, directory: str | Path) -> tuple[Path, Path]:
    """Write ``sysid_report.json`` and ``sysid_report.png`` (loss curves, per-frame tracking error,
    stiffness histogram, identifiability intervals, notes) into ``directory``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    rep = report_dict(result, data)
    jpath = directory / "sysid_report.json"
    jpath.write_text(json.dumps(rep, indent=2) + "\n")

    fig, ax = plt.subplots(2, 3, figsize=(16, 7.5))
    a = ax[0, 0]
    if result.stage1_history:
        start = 0
        for stage, h in (("stage 1", result.stage1_history), ("stage 3", result.stage3_history),
                         ("stage 4", result.stage4_history)):
            if not h:
                continue
            a.semilogy([start + r["evaluation"] for r in h], [r["best"] for r in h],
                       label=f"{stage}: best so far")
            a.semilogy([start + r["evaluation"] for r in h], [r["loss"] for r in h], ".", ms=3, alpha=0.5,
                       label=f"{stage}: candidate")
            start += len(h)
        a.legend()
    else:
        a.text(0.5, 0.5, "stage 1 off", ha="center", va="center", transform=a.transAxes)
    a.set(title="CMA-ES (stages 1, 3, 4): Chamfer + tracking loss", xlabel="evaluation")
    a = ax[0, 1]
    rows = [r for r in result.stage2_history if "train_loss" in r]
    if rows:
        ep = [r["epoch"] for r in rows]
        h1 = a.semilogy(ep, [r["train_loss"] for r in rows], "o-", label="training loss (all terms)")
        a2 = a.twinx()
        h2 = a2.plot(ep, [1e3 * r["val_error"] for r in rows], "s--", color="C1", label="validation error")
        a2.set_ylabel("validation tracking error (mm)")
        a.legend(handles=h1 + h2, loc="upper right")
    else:
        a.text(0.5, 0.5, "stage 2 off", ha="center", va="center", transform=a.transAxes)
    a.set(title="stage 2: Adam on per-spring log Y", xlabel="epoch")
    a = ax[1, 0]
    for name, e in result.evals.items():
        a.plot(np.arange(e.track_error.size), 1e3 * e.track_error,
               label=f"{name} (validation {1e3 * e.val_error:.2f} mm)")
    if data.validation_frames:
        a.axvspan(data.val_frames.start - 0.5, data.num_frames - 0.5, color="0.9", label="validation frames")
    a.set(title="tracking error per frame", xlabel="frame", ylabel="mm")
    a.legend(fontsize=8)
    a = ax[1, 1]
    ys = result.object_spring_Y
    if ys.size:
        a.hist(np.log10(ys), bins=30)
    a.set(title=f"object spring stiffness ({ys.size} springs)", xlabel="log10 Y", ylabel="springs")
    _identifiability_panel(ax[0, 2], result)
    a = ax[1, 2]
    a.axis("off")
    a.set_title("notes")
    a.text(0.0, 1.0, "\n\n".join(textwrap.fill(n, 60) for n in result.notes) or "none", va="top", fontsize=9,
           transform=a.transAxes)
    kept, frames = result.selection.get("kept"), result.selection.get("frames")
    why = f"by the selection frames {frames[0]}-{frames[1]}" if frames else "the last stage run"
    fig.suptitle(f"system identification: {data.name}" + (f" (kept: {kept}, {why})" if kept else ""))
    fig.tight_layout()
    ppath = directory / "sysid_report.png"
    fig.savefig(ppath, dpi=90)
    plt.close(fig)
    return jpath, ppath
