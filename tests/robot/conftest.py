"""Fixtures for the robot tests: the built-in arm with each tool (loaded once)."""

from __future__ import annotations

import pytest

from twinbench.robot.builtin import load_builtin_arm


@pytest.fixture(scope="session")
def arm():
    return load_builtin_arm("gripper")


@pytest.fixture(scope="session")
def pusher_arm():
    return load_builtin_arm("pusher")
