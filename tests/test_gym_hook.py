"""The gymnasium registration hook (src/twinbench-gym.pth + src/_twinbench_gym_hook.py): in a fresh
interpreter `gymnasium.make("twinbench/PushT-v0")` works without importing twinbench, nothing is imported
at start, the hook can be switched off and never breaks `import gymnasium`."""

from __future__ import annotations

import os
import site
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
INSTALLED = [Path(p) / "twinbench-gym.pth" for p in site.getsitepackages()]
pytestmark = pytest.mark.skipif(
    not any(p.is_file() for p in INSTALLED),
    reason="twinbench-gym.pth is not installed in this environment (install twinbench: make install)",
)


def _python(code: str, **env) -> subprocess.CompletedProcess:
    clean = {k: v for k, v in os.environ.items() if not k.startswith("TWINBENCH_")}
    return subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True,
                          env={**clean, **env}, timeout=300, cwd=Path(__file__).parent)


def test_the_installed_hook_is_the_one_in_the_source_tree():
    installed = next(p for p in INSTALLED if p.is_file())
    assert installed.read_text() == (SRC / "twinbench-gym.pth").read_text()


def test_nothing_is_imported_at_start_and_a_bare_id_makes_the_env():
    out = _python("import sys; print(sorted(m for m in ('twinbench', 'gymnasium', '_twinbench_gym_hook') "
                  "if m in sys.modules))")
    assert out.returncode == 0 and out.stdout.strip() == "[]", out.stderr
    out = _python("import gymnasium as g\n"
                  "env = g.make('twinbench/PushT-v0', preset='fast')\n"
                  "obs, info = env.reset(seed=0)\n"
                  "print(type(env.unwrapped).__name__, obs['agent_pos'].shape)")
    assert out.returncode == 0, out.stderr
    assert out.stdout.split()[-2:] == ["TwinEnv", "(2,)"]


def test_import_twinbench_first_still_registers_once_without_warnings():
    out = _python("import twinbench, gymnasium\n"
                  "print(sum(k.startswith('twinbench/') for k in gymnasium.registry))")
    assert out.returncode == 0, out.stderr  # -W error: a re-registration warning would fail
    assert out.stdout.strip() == "4"


def test_the_hook_can_be_switched_off():
    out = _python("import gymnasium as g\ng.make('twinbench/PushT-v0')", TWINBENCH_NO_GYM_HOOK="1")
    assert out.returncode != 0 and "NamespaceNotFound" in out.stderr


def test_a_broken_twinbench_never_breaks_import_gymnasium(tmp_path):
    broken = tmp_path / "twinbench"
    broken.mkdir()
    (broken / "__init__.py").write_text("raise RuntimeError('broken install')\n")
    code = "import gymnasium\nprint(gymnasium.__name__, 'twinbench/PushT-v0' in gymnasium.registry)"
    out = _python(code, PYTHONPATH=str(tmp_path))
    assert out.returncode == 0 and out.stdout.strip() == "gymnasium False", out.stderr
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                         env={**os.environ, "PYTHONPATH": str(tmp_path), "TWINBENCH_DEBUG_GYM_HOOK": "1"})
    assert out.returncode == 0 and "broken install" in out.stderr


@pytest.mark.parametrize("init", ["import sys\nsys.exit(3)\n", "raise SystemExit('bye')\n",
                                  "raise KeyError(1)\n"])
def test_twinbench_ending_its_import_never_ends_import_gymnasium(tmp_path, init):
    (tmp_path / "twinbench").mkdir()
    (tmp_path / "twinbench" / "__init__.py").write_text(init)
    out = _python("import gymnasium\nprint('alive', gymnasium.__name__)", PYTHONPATH=str(tmp_path))
    assert out.returncode == 0 and out.stdout.strip() == "alive gymnasium", out.stderr


@pytest.mark.parametrize("hook", [None, "def find_spec(:\n", "raise SystemExit(4)\n",
                                  "raise ImportError('x')\n"],
                         ids=["missing", "syntax-error", "system-exit", "import-error"])
def test_a_missing_or_broken_hook_module_never_breaks_import_gymnasium(tmp_path, hook):
    if hook is None:  # a half-uninstalled twinbench: the .pth is there, the module is not
        code = "import sys\nsys.modules['_twinbench_gym_hook'] = None\n"
        env = {}
    else:  # a broken module of that name found first
        (tmp_path / "_twinbench_gym_hook.py").write_text(hook)
        code, env = "", {"PYTHONPATH": str(tmp_path)}
    out = _python(code + "import gymnasium, json\nprint('alive', json.dumps(2))", **env)
    assert out.returncode == 0 and out.stdout.strip() == "alive 2", out.stderr
