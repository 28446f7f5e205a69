"""Every optional extra imports when installed, and what is installed satisfies pyproject's ranges."""

import importlib
import importlib.metadata
import importlib.util
import sys
import tomllib
from pathlib import Path

import pytest
from packaging.markers import default_environment
from packaging.requirements import Requirement

ROOT = Path(__file__).resolve().parents[1]
PYPROJECT = tomllib.loads((ROOT / "pyproject.toml").read_text())
# extra -> the modules it provides (example-robot-data is data: the xArm 7 URDF, found by distribution)
EXTRA_MODULES = {
    "dev": ["pytest", "pytest_timeout", "ruff"],
    "torch": ["torch"],
    "gsplat": ["torch", "gsplat"],
    "xarm": [],
    "ray": ["ray"],
    "lerobot": ["lerobot", "lerobot.scripts.lerobot_eval", "lerobot_env_twinbench"],
}


def _requirements(extra: str | None) -> list[Requirement]:
    deps = PYPROJECT["project"]["dependencies"] if extra is None else (
        PYPROJECT["project"]["optional-dependencies"][extra])
    return [Requirement(d) for d in deps]


def _check_installed_versions(reqs: list[Requirement]) -> None:
    env = default_environment()
    for req in reqs:
        if req.marker is not None and not req.marker.evaluate(env):
            continue
        version = importlib.metadata.version(req.name)
        assert req.specifier.contains(version, prereleases=True), (
            f"{req.name} {version} is installed but pyproject asks for {req}: run `make install` (uv.lock)")


def _installed(dist: str) -> bool:
    try:
        importlib.metadata.version(dist)
        return True
    except importlib.metadata.PackageNotFoundError:
        return False


def test_every_extra_has_an_import_test():
    assert set(PYPROJECT["project"]["optional-dependencies"]) == set(EXTRA_MODULES)


def test_core_versions_satisfy_the_ranges():
    _check_installed_versions(_requirements(None))


@pytest.mark.parametrize("extra", sorted(EXTRA_MODULES))
def test_extra_imports(extra):
    if extra == "lerobot" and sys.version_info < (3, 12):
        pytest.skip("the lerobot extra needs Python >= 3.12 (LeRobot 0.6)")
    missing = [m for m in EXTRA_MODULES[extra] if importlib.util.find_spec(m.split(".")[0]) is None]
    missing += [r.name for r in _requirements(extra) if not _installed(r.name) and r.name not in missing]
    if missing:
        pytest.skip(f"extra {extra!r} not installed ({missing} missing): make install EXTRAS='dev {extra}'")
    _check_installed_versions(_requirements(extra))
    for module in EXTRA_MODULES[extra]:
        importlib.import_module(module)
    if extra == "xarm":
        from twinbench.robot.builtin import xarm7_urdf_path

        assert xarm7_urdf_path().is_file()
    if extra == "lerobot":
        from lerobot.envs.configs import EnvConfig
        from lerobot.utils.import_utils import register_third_party_plugins

        register_third_party_plugins()  # what lerobot-eval does: finds the distribution by its name
        assert EnvConfig.get_choice_class("twinbench").__module__ == "lerobot_env_twinbench"
