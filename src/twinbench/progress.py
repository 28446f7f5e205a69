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


def _duration(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s // 60 % 60:02d}:{s % 60:02d}"


class ProgressLines:
    """Progress as plain lines, for output that is not a terminal (nohup, CI, a cluster job's log), where the
    bar draws nothing until the run ends: `log`s "DESC: done/total (info), elapsed H:MM:SS, ETA H:MM:SS" at
    most every `every_s` seconds, and at the end of a run that printed any (a short run prints none). The
    ETA is from the items done since this object was made (a resumed run's earlier ones do not count)."""

    def __init__(self, log, desc: str, total: int, done: int = 0, every_s: float = 60.0, clock=None):
        import time

        self.log, self.desc, self.total, self.every_s = log, desc, int(total), float(every_s)
        self.clock = clock or time.monotonic
        self.t0 = self.last = self.clock()
        self.done0 = int(done)
        self.printed = False

    def update(self, done: int, info=None) -> None:
        """`info`: a function giving the line's extra text, called only when a line is printed."""
        now = self.clock()
        end = done >= self.total
        if not (now - self.last >= self.every_s or (end and self.printed)):
            return
        self.last, self.printed = now, True
        elapsed = now - self.t0
        rate = (done - self.done0) / elapsed if elapsed > 0 else 0.0
        eta = "-" if rate <= 0 else _duration((self.total - done) / rate)
        text = info() if info is not None else ""
        extra = f" ({text})" if text else ""
        self.log(f"{self.desc}: {done}/{self.total}{extra}, elapsed {_duration(elapsed)}, ETA {eta}")
