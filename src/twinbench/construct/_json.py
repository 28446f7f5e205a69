"""The construction tools' small JSON outputs (reports, metadata)."""

from __future__ import annotations

import json
from pathlib import Path


def write_json(path: Path, doc) -> None:
    """Write ``doc`` as indented JSON at ``path`` (creating its folder)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=1) + "\n")
