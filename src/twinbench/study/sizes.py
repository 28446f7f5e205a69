"""How much a study makes and evaluates (`twinbench study ... --size small|medium|full`)."""

from __future__ import annotations

from dataclasses import dataclass

from twinbench.errors import InputError


@dataclass(frozen=True)
class StudySize:
    """Grid states evaluated (None: all), episode length (None: the task's), colour-calibration images, the
    built-in cell the real workcell derives from, (frames, validation frames) of each probe's motion, and
    whether the real workcell is evaluated a second time with other episode seeds (`real_again`: how well
    one real evaluation predicts another of the same size, the yardstick for the twins' r and MMRV)."""

    states: tuple[int, ...] | None
    episode_seconds: float | None
    calibration_images: int
    preset: str = "fast"
    motion_frames: tuple[int, int] = (45, 10)
    real_again: bool = False


SIZES = {
    # the expert succeeds within 299 steps (10 s), then >= 30 of the last 100 frames: 15 s episodes; no
    # second real evaluation (toy packing's would take the study past an hour on 2 cores)
    "small": StudySize((0, 9), 15.0, 4),
    # the same workcell and twins as small (fast cell), every other grid state
    "medium": StudySize(tuple(range(0, 16, 2)), 15.0, 8, real_again=True),
    "full": StudySize(None, None, 8, preset="reference", motion_frames=(90, 20), real_again=True),
}


def size_name(size: str | StudySize) -> str:
    """The size's name as files record it ("custom" for a StudySize given directly, e.g. a test's)."""
    return size if isinstance(size, str) else "custom"


def study_size(size: str | StudySize) -> StudySize:
    """The named size (or `size` itself when it is a StudySize, e.g. a test's tiny one)."""
    if isinstance(size, StudySize):
        return size
    if size not in SIZES:
        raise InputError(f"study size {size!r} (--size): give one of {sorted(SIZES)}")
    return SIZES[size]
