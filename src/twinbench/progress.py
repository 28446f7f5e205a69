"""The progress bar long runs show (evaluation, system identification): description, bar, done/total,
elapsed time and ETA, plus optional extra text columns."""

from __future__ import annotations


def progress_bar(enabled: bool = True, *extra_columns: str):
    """A rich Progress; `extra_columns` are format strings such as "{task.fields[info]}"."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    return Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                    TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                    *(TextColumn(c) for c in extra_columns), disable=not enabled)
