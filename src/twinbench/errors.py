"""twinbench's error family: every error the package raises on purpose is a `TwinbenchError`.

- `InputError` (a `ValueError`): a file, an argument or a message that cannot be used as given; its text
  names the file or field and the fix. Every format error (`GaussianFileError`, `URDFError`,
  `TwinFormatError`, `PhysTwinFormatError`, `SysIdFormatError`, `MessageError`) subclasses it, and
  `twinbench <command>` prints it as one line (exit code 2).
- `SimulationDiverged` (a `RuntimeError`): particles became non-finite or too fast; the episode ends with
  status `sim_error`.
- `PolicyError` (a `RuntimeError`): a policy failed to produce an action (crash, unreachable server, bad
  output); the episode ends with status `policy_error`.
- `StorageError` (an `OSError`): the machine could not keep a result (disk full, read-only file system);
  its text names the file, the free space and the fix (exit code 1).
"""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np

_NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.\-]{0,127}$")


class TwinbenchError(Exception):
    """Base of every error twinbench raises on purpose."""


class InputError(TwinbenchError, ValueError):
    """Bad input (a file, an argument, a message): the message names it and the fix."""


class SimulationDiverged(TwinbenchError, RuntimeError):
    """The simulation diverged (non-finite or too fast particles; ``indices`` lists them, may be empty)."""

    def __init__(self, indices=(), reason: str = ""):
        self.indices = np.asarray(indices, dtype=np.int64).reshape(-1)
        if self.indices.size == 0:  # a divergence found otherwise (energy, a task's own check)
            super().__init__(f"simulation diverged{': ' if reason and reason[0] != ':' else ''}{reason}")
            return
        shown = self.indices[:10].tolist()
        more = "" if self.indices.size <= 10 else f" (+{self.indices.size - 10} more)"
        super().__init__(f"simulation diverged at {self.indices.size} particle(s) {shown}{more}{reason}")


class PolicyError(TwinbenchError, RuntimeError):
    """A policy failed to produce an action (crash, unreachable server, bad output): policy_error."""


class StorageError(TwinbenchError, OSError):
    """The machine could not keep a result (disk full, read-only or vanished folder); what was committed
    before stays."""


def free_space(path) -> str:
    """The free space on the file system holding `path` (its nearest existing folder), for messages."""
    folder = Path(path)
    while not folder.is_dir() and folder != folder.parent:
        folder = folder.parent
    try:
        free = shutil.disk_usage(folder).free
    except OSError:
        return "free space unknown"
    return f"{free / 2**20:.1f} MiB free on {folder}" if free >= 2**20 else f"{free} bytes free on {folder}"


def check_name(value, what: str) -> str:
    """The one rule for a name that becomes a file or folder name (run ids, twin, object, collider, camera
    and box names): letters, digits, '_', '.', '-', at most 128, not starting with '.' or '-', so it can
    never be a path. Returns it; `InputError` naming `what` otherwise."""
    if not isinstance(value, str) or not _NAME_RE.fullmatch(value):
        raise InputError(f"{what} {value!r}: use a name of letters, digits, '_', '.', '-' (no '/', no "
                         "leading '.' or '-', at most 128 characters), e.g. 'push-t_2024-05-01'")
    return value
