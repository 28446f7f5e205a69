"""Registers twinbench's gymnasium env ids whenever gymnasium is imported, so that
`gymnasium.make("twinbench/PushT-v0")` works in any interpreter of an environment where twinbench is
installed, without `import twinbench` first (gymnasium >= 1.0 loads no plugin entry points).

`twinbench-gym.pth` (installed beside this module) runs one line at interpreter start: unless
TWINBENCH_NO_GYM_HOOK is set, it puts a stub finder on `sys.meta_path` that does nothing for any module
but `gymnasium` (nothing is imported at start, not even this module). On `import gymnasium` the stub calls
`find_spec` here, which removes the stub, lets the real finders locate gymnasium and wraps its loader:
gymnasium loads as usual, then twinbench is imported (light: its task modules declare the ids; Warp loads
only when an env is made) and registers its ids.
A failure never breaks or ends the import of gymnasium: an exception or a SystemExit of twinbench's import
is ignored (TWINBENCH_DEBUG_GYM_HOOK=1 shows it as a warning), and the .pth's stub drops itself and lets
gymnasium load when this module is missing or broken.
"""

import os
import sys

STUB = "TwinbenchGymHook"  # the class name of the .pth's stub finder


def find_spec(fullname: str):
    """gymnasium's module spec with a loader that registers twinbench's ids after gymnasium ran."""
    sys.meta_path[:] = [f for f in sys.meta_path if type(f).__name__ != STUB]  # once is enough
    try:
        import importlib.util

        spec = importlib.util.find_spec(fullname)
        if spec is None or spec.loader is None or not hasattr(spec.loader, "exec_module"):
            return spec
        real_exec = spec.loader.exec_module

        def exec_module(module):
            real_exec(module)
            register()

        spec.loader.exec_module = exec_module
        return spec
    except (Exception, SystemExit) as err:  # noqa: BLE001 - never break `import gymnasium`
        _debug(err)
        return None


def register() -> None:
    """Register twinbench's env ids (what `import twinbench` does); failures are ignored."""
    try:
        import twinbench

        twinbench.register_envs()
    except (Exception, SystemExit) as err:  # noqa: BLE001 - a broken twinbench must not break gymnasium
        _debug(err)


def _debug(err: BaseException) -> None:
    if os.environ.get("TWINBENCH_DEBUG_GYM_HOOK"):
        import warnings

        warnings.warn(f"twinbench gymnasium hook: {err!r}", stacklevel=2)
