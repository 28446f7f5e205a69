"""Shared test fixtures: the golden-data folder and device selection."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED = Path(__file__).resolve().parents[1].parent / "shared"


@pytest.fixture(scope="session")
def phystwin_reference() -> Path:
    """Folder with PhysTwin's golden trajectories; skips with a reason when ../shared is absent."""
    folder = SHARED / "reference" / "phystwin"
    if not folder.is_dir():
        pytest.skip(f"golden data not found at {folder} (clone the repo beside ../shared to run this)")
    return folder


def _cuda_available() -> bool:
    import warp as wp

    wp.init()
    return wp.get_cuda_device_count() > 0


def pytest_collection_modifyitems(config, items):
    if any("gpu" in item.keywords for item in items) and not _cuda_available():
        skip = pytest.mark.skip(reason="needs a CUDA device; none is present on this machine")
        for item in items:
            if "gpu" in item.keywords:
                item.add_marker(skip)


@pytest.fixture(scope="session")
def fast_env():
    """A push-T env on the built-in `fast` cell with early termination on success (quick expert
    episodes), built once per session (each test resets it)."""
    from twinbench.env import TwinEnv

    env = TwinEnv("push-t", preset="fast", success_rule="early")
    env.reset(seed=0, options={"init_state": 0})
    return env
