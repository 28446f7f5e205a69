"""Episode videos: an MP4 written frame by frame as an episode runs, and the check that a file is a
complete MP4 (a file cut short by a full disk is not)."""

from __future__ import annotations

import struct
import traceback
import warnings
from pathlib import Path

import numpy as np


def error_text(err: BaseException) -> str:
    """'Type: message' of an exception, as episodes store their errors (and videos the reason they are
    missing)."""
    return "".join(traceback.format_exception_only(type(err), err)).strip()


class VideoWriter:
    """Streams frames to an MP4 as they come (an episode's frames never sit in memory at once).

    A failing writer (disk full, ffmpeg error) never affects the episode: writing stops, `close()` reports
    the video as missing with the reason, and a file that is not a complete MP4 is deleted."""

    def __init__(self, path: str | Path, env):
        self.path = Path(path)
        self.fps = env.unwrapped.metadata.get("render_fps", 30)
        self._writer = None
        self.error: str | None = None

    def add(self, frame) -> None:
        if self.error is not None:
            return
        try:
            if self._writer is None:
                import imageio.v2 as imageio

                self.path.parent.mkdir(parents=True, exist_ok=True)
                self._writer = imageio.get_writer(str(self.path), fps=self.fps)
            self._writer.append_data(np.asarray(frame))
        except Exception as err:  # noqa: BLE001 - a video failure is reported, not an episode failure
            self.error = f"writing {self.path}: {error_text(err)}"

    def close(self) -> tuple[bool, str | None]:
        """Finish the file -> (whether a complete video was written, why not)."""
        if self._writer is None:
            return False, self.error
        try:
            self._writer.close()
        except Exception as err:  # noqa: BLE001
            self.error = self.error or f"finishing {self.path}: {error_text(err)}"
        if self.error is None and not mp4_complete(self.path):
            self.error = f"{self.path} is truncated (incomplete MP4; disk full?)"
        if self.error is not None:
            self.path.unlink(missing_ok=True)
            warnings.warn(f"video missing: {self.error}", stacklevel=2)
            return False, self.error
        return True, None


def mp4_complete(path: str | Path) -> bool:
    """Whether `path` is a complete MP4: its top-level boxes tile the file exactly and include ftyp, mdat
    and moov (a file cut short by a full disk fails this)."""
    path = Path(path)
    try:
        size, seen, pos = path.stat().st_size, set(), 0
        with path.open("rb") as fh:
            while pos < size:
                fh.seek(pos)
                head = fh.read(8)
                if len(head) < 8:
                    return False
                n, kind = struct.unpack(">I4s", head)
                if n == 1:
                    ext = fh.read(8)
                    if len(ext) < 8:
                        return False
                    n = struct.unpack(">Q", ext)[0]
                elif n == 0:
                    n = size - pos
                if n < 8 or pos + n > size:
                    return False
                seen.add(kind)
                pos += n
    except OSError:
        return False
    return {b"ftyp", b"mdat", b"moov"} <= seen
