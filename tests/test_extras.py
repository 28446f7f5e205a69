"""Every optional extra imports when installed, and what is installed satisfies pyproject's ranges."""

import importlib
import importlib.metadata
import importlib.util
import os
import shutil
import subprocess
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
    "lerobot": ["lerobot", "lerobot.scripts.lerobot_eval", "lerobot_env_twinbench", "diffusers",
                "lerobot.policies.act.modeling_act", "lerobot.policies.diffusion.modeling_diffusion"],
    "smolvla": ["transformers", "accelerate", "num2words", "lerobot.policies.smolvla.modeling_smolvla"],
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
    if extra in ("lerobot", "smolvla") and sys.version_info < (3, 12):
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


def test_uv_lock_matches_pyproject():
    """uv.lock resolves every extra of pyproject.toml (`make lock` after editing a range)."""
    uv = ROOT / ".tools" / "bin" / "uv"
    if not uv.is_file():
        pytest.skip("uv is not in .tools (run make)")
    out = subprocess.run([str(uv), "lock", "--check", "--offline"], cwd=ROOT, capture_output=True, text=True,
                         env={**os.environ, "UV_PYTHON_DOWNLOADS": "never"}, timeout=120)
    assert out.returncode == 0, out.stderr


@pytest.mark.parametrize("stamp, extras", [("dev lerobot\n", "--extra dev --extra lerobot"),
                                           ("dev torch gsplat\n",
                                            "--extra dev --extra torch --extra gsplat")])
def test_make_resyncs_with_the_installed_extras(tmp_path, stamp, extras):
    """After a pull that changes uv.lock, `make test` re-syncs with the extras of the last install, exactly
    (nothing removed), and says so."""
    if shutil.which("make") is None:
        pytest.skip("no make")
    venv = tmp_path / "venv"
    venv.mkdir()
    (venv / ".installed").write_text(stamp)
    os.utime(venv / ".installed", (0, 0))  # older than uv.lock: as after a pull
    out = subprocess.run(["make", "-n", "-C", str(ROOT), f"VENV={venv}", "test"], capture_output=True,
                         text=True, timeout=60, env={k: v for k, v in os.environ.items() if k != "EXTRAS"})
    assert out.returncode == 0, out.stderr
    sync = [line for line in out.stdout.splitlines() if " sync --locked " in line]
    assert len(sync) == 1 and sync[0].rstrip().endswith(extras), out.stdout
    assert f"re-syncing it with the same extras: {stamp.strip()}" in out.stdout
    assert f'echo "{stamp.strip()}" > {venv}/.installed' in out.stdout


def test_make_keeps_everything_with_an_old_empty_stamp(tmp_path):
    """A stamp written before extras were remembered (empty): dev + lerobot when lerobot-eval is installed,
    and uv removes nothing (--inexact)."""
    if shutil.which("make") is None:
        pytest.skip("no make")
    venv = tmp_path / "venv"
    (venv / "bin").mkdir(parents=True)
    (venv / "bin" / "lerobot-eval").write_text("")
    (venv / ".installed").write_text("")
    os.utime(venv / ".installed", (0, 0))
    out = subprocess.run(["make", "-n", "-C", str(ROOT), f"VENV={venv}", "test"], capture_output=True,
                         text=True, timeout=60, env={k: v for k, v in os.environ.items() if k != "EXTRAS"})
    sync = [line for line in out.stdout.splitlines() if " sync --locked " in line]
    assert len(sync) == 1 and sync[0].rstrip().endswith("--extra dev --extra lerobot --inexact"), out.stdout
