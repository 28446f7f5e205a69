"""`twinbench report`: write a self-contained HTML report of an evaluation run."""

from __future__ import annotations

import sys
from dataclasses import dataclass
from pathlib import Path

from twinbench.evaluation.report import VideoLimits, write_report
from twinbench.evaluation.store import DEFAULT_DB, ResultsStore


@dataclass(frozen=True)
class ReportConfig:
    """Write a self-contained HTML report of an evaluation run."""

    run_id: str
    """evaluation run to report."""
    db: Path = DEFAULT_DB
    """results store (SQLite)."""
    real_run_id: str | None = "real"
    """run id of imported real outcomes (None: no sim-vs-real comparison)."""
    replay_run_id: str | None = "replay"
    """run id of `twinbench replay` results (replay vs real confusion matrices)."""
    out: Path = Path("report.html")
    """output HTML file."""
    max_videos: int = 12
    """most rollout videos embedded."""
    strict: bool = False
    """refuse (exit 2) when real or replay episodes come from another task or grid than the run (default:
    leave them out or flag them, with a warning on the console and a red banner in the report)."""


def main(config: ReportConfig) -> int:
    try:
        path = write_report(ResultsStore(config.db), config.run_id, config.out,
                            real_run_id=config.real_run_id, replay_run_id=config.replay_run_id,
                            videos=VideoLimits(max_videos=config.max_videos), strict=config.strict,
                            warn=lambda m: print(f"twinbench report: WARNING: {m}", file=sys.stderr))
    except ValueError as err:
        print(f"twinbench report: {err}", file=sys.stderr)
        return 2
    print(f"wrote {path} ({path.stat().st_size / 2**20:.1f} MiB)")
    return 0
