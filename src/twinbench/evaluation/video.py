"""Episode videos: an MP4 written frame by frame as an episode runs (every camera side by side unless
views are chosen), and the check that a file is a complete MP4 (a file cut short by a full disk is not).

A video is written under a temporary name (`partial_path`) and renamed to its final name only once it
is complete, so an interrupted or failed episode never leaves a partial file under the final name; the
runner removes the temporary files of episodes still in flight when a run is interrupted."""

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


ALL_VIEWS = "all"


def partial_path(path: str | Path) -> Path:
    """The temporary name a video is written under until it is complete: `NAME.partial.mp4`."""
    path = Path(path)
    return path.with_name(f"{path.stem}.partial{path.suffix or '.mp4'}")


def choose_views(env, views: str) -> list[str] | None:
    """The cameras a video shows: every camera of `env`'s `pixels` observation for "all", else the named
    ones ("front+wrist"); None for an env without per-camera pixels (its `render()` is used). Raises
    InputError for a camera the env does not have."""
    from twinbench.errors import InputError

    space = getattr(env, "observation_space", None)
    pixels = space.spaces.get("pixels") if hasattr(space, "spaces") else None
    names = list(pixels.spaces) if hasattr(pixels, "spaces") else None
    if names is None:
        return None
    if views == ALL_VIEWS:
        return names
    chosen = [v for v in views.split("+") if v]
    unknown = [v for v in chosen if v not in names]
    if unknown or not chosen:
        raise InputError(f"--video-views {views!r}: unknown camera(s) {unknown or chosen}; give 'all' or "
                         f"cameras joined by '+' from {names}")
    return chosen


def video_frame(obs, env, views: list[str] | None) -> np.ndarray:
    """One video frame: the `views` cameras of `obs["pixels"]` side by side (shorter images padded with
    black at the bottom), or `env.render()` when `views` is None."""
    if views is None:
        return np.asarray(env.render())
    frames = [np.asarray(obs["pixels"][v]) for v in views]
    h = max(f.shape[0] for f in frames)
    frames = [np.pad(f, ((0, h - f.shape[0]), (0, 0), (0, 0))) if f.shape[0] < h else f for f in frames]
    return frames[0] if len(frames) == 1 else np.concatenate(frames, axis=1)


class VideoWriter:
    """Streams frames to an MP4 as they come (an episode's frames never sit in memory at once).

    A failing writer (disk full, ffmpeg error) never affects the episode: writing stops, `close()` reports
    the video as missing with the reason, and a file that is not a complete MP4 is deleted. Frames go to
    `partial_path(path)`, renamed to `path` by `close()` once complete; `abort()` deletes them."""

    def __init__(self, path: str | Path, env):
        self.path = Path(path)
        self.tmp = partial_path(self.path)
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
                self._writer = imageio.get_writer(str(self.tmp), fps=self.fps)
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
        if self.error is None and not mp4_complete(self.tmp):
            self.error = f"{self.path} is truncated (incomplete MP4; disk full?)"
        if self.error is None:
            try:
                self.tmp.replace(self.path)
            except OSError as err:
                self.error = f"renaming {self.tmp} to {self.path}: {error_text(err)}"
        if self.error is not None:
            self.tmp.unlink(missing_ok=True)
            warnings.warn(f"video missing: {self.error}", stacklevel=2)
            return False, self.error
        return True, None

    def abort(self) -> None:
        """Stop writing and delete the unfinished file (an episode interrupted mid-way)."""
        writer, self._writer = self._writer, None
        if writer is not None:
            try:
                writer.close()
            except Exception:  # noqa: BLE001 - the file is deleted anyway
                pass
        self.tmp.unlink(missing_ok=True)


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
