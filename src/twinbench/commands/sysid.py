"""`twinbench sysid --data cases/rope`: fit an object's physics to observed motion (the fit is
twinbench.physics.sysid; the files are twinbench.construct.sysid_io and sysid_report)."""

from __future__ import annotations

from dataclasses import dataclass, replace
from pathlib import Path
from typing import Literal

from twinbench.construct.sysid_io import load_input, write_object_dir
from twinbench.construct.sysid_report import write_report
from twinbench.errors import SimulationDiverged
from twinbench.physics.sysid import FitConfig, identify
from twinbench.physics.sysid_data import SysIdFormatError, observed_masses
from twinbench.physics.sysid_guess import tool_contact_distance


@dataclass(frozen=True, kw_only=True)
class SysIdConfig(FitConfig):
    """`twinbench sysid`: identify an object's physics from observed motion (see sysid_data for the
    input directory). Writes ``<out_dir>/<name>/`` (object.json + npz) and ``sysid_report.{json,png}``."""

    data: Path
    """sysid input directory (sysid.json + npz, see twinbench.construct.sysid_io), or a PhysTwin case
    folder / its final_data.pkl (read with the restricted loader of twinbench.construct.phystwin)"""
    out_dir: Path = Path("outputs/sysid")
    masses: Literal["data", "observed"] = "data"
    """particle masses: "data" (the data's `masses`, else 1 each, as PhysTwin); "observed" (in proportion to
    the share of frame 0's observed points each particle stands for, the same total: for particles that
    sample the object unevenly, e.g. a voxel pick of a finer cloud; see sysid_data.observed_masses)"""
    measure_mesh_margin: bool = False
    """a push recording (data with a tool): fit with the tool's contact distance measured from it (the
    nearest observed point's distance to the tool while it carries the object, see
    sysid_guess.tool_contact_distance) instead of --mesh-margin; the report's config holds the value"""


def main(cfg: SysIdConfig) -> int:
    """Load, identify, write the object directory and the fit report."""
    from rich.console import Console

    console = Console(stderr=True)

    def say(msg: str) -> None:
        console.print(msg, markup=False, soft_wrap=True, highlight=False)

    try:
        data = load_input(cfg.data)
        if cfg.masses == "observed":
            data = replace(data, masses=observed_masses(data))
            say(f"masses by observed share: {data.masses.min():.2f}-{data.masses.max():.2f} (mean 1)")
        if cfg.measure_mesh_margin:
            margin, frames = tool_contact_distance(data)
            cfg = replace(cfg, mesh_margin=margin)
            say(f"tool contact distance measured from the push: {1e3 * margin:.2f} mm (median over the "
                f"{len(frames)} frames where the tool carries the object, {frames.min()}-{frames.max()})")
        result = identify(data, cfg, log=say)
    except (SysIdFormatError, ValueError) as exc:
        say(f"twinbench sysid: {exc}")
        return 2
    except SimulationDiverged as exc:
        say(f"twinbench sysid: {exc}")
        return 1
    obj = write_object_dir(result, data, cfg.out_dir / data.name)
    jpath, ppath = write_report(result, data, cfg.out_dir)
    for name, e in result.evals.items():
        say(f"{name:>8}: training loss {e.train_loss:.4e}, tracking error: training "
            f"{1e3 * e.train_error:.2f} mm, validation {1e3 * e.val_error:.2f} mm")
    if result.selection:
        say(f"kept: {result.selection['kept']} ({result.selection['rule']})")
        if "second_start" in result.selection:
            say("second start (stage 1 scoring the control attachments before its search): "
                f"{result.selection['second_start']}")
        for start in result.selection.get("starts", []):
            say(f"start (stage 1 {start['stage1']}): training tracking error "
                f"{1e3 * start['train_error_m']:.2f} mm{', kept' if start['kept'] else ''}")
    if data.has_tool:
        say(f"tool contact: friction {result.params.tool_friction:.3f}, restitution "
            f"{result.params.tool_restitution:.3f} (a twin's robot.tool_contact)")
    if result.identifiability:
        fixed = [k for k, v in result.identifiability.items() if v["constrained"]]
        loose = [k for k, v in result.identifiability.items() if not v["constrained"]]
        kept = [k for k, v in result.identifiability.items() if v.get("guess_kept")]
        say(f"constrained by the motion: {', '.join(fixed) or 'none'}; weakly: {', '.join(loose) or 'none'} "
            "(intervals in the report)" + (f"; measured value kept: {', '.join(kept)}" if kept else ""))
    rows = result.region_identifiability.get("regions", [])
    if rows:
        fixed = sum(r["constrained"] for r in rows)
        say(f"stiffness regions constrained by the motion: {fixed} of {len(rows)} (log Y within "
            f"{result.region_identifiability['std_limit']:.2f} at one standard deviation; the others' "
            "values are not determined by the motion)")
    say(f"object: {obj}\nreport: {jpath}, {ppath}")
    return 0
