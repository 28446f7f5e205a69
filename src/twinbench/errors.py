"""The project's error type for bad input: a file or an argument that cannot be used as given.

`InputError` is a `ValueError`, so callers that catch ValueError keep working. Its message names the
file or argument and says how to fix it; `twinbench <command>` prints it as one line (exit code 2).
Format-specific errors (`GaussianFileError`, `URDFError`, ...) subclass it.
"""

from __future__ import annotations


class InputError(ValueError):
    """Bad input (a file, an argument, a message): the message names it and the fix."""
