"""`twinbench <command>`: the entry point. Each command is a module of `twinbench.commands` (its tyro config
and its `main`), imported only when that command runs; errors print as one line (see `_report_error`)."""

from __future__ import annotations

import errno
import importlib
import os
import sys

from twinbench._runtime import quiet_warp

# command -> (module, config dataclass, function taking the config, one-line description)
COMMANDS: dict[str, tuple[str, str, str, str]] = {
    "demo": ("twinbench.commands.demo", "DemoConfig", "main",
             "evaluate scripted policies on a built-in twin (push-T; --task rope-routing | toy-packing)"),
    "twin": ("twinbench.commands.twin", "TwinCommand", "main",
             "twin export (a task's built-in twin as a directory) | twin show (summary + camera PNGs) | "
             "twin build (a twin directory from a build config)"),
    "physics-demo": ("twinbench.commands.physics_demo", "DemoConfig", "main",
                     "soft cube dropped, grasped and lifted"),
    "render-ply": ("twinbench.commands.render_ply", "RenderPlyConfig", "main",
                   "render a 3DGS .ply/.splat/.spz to a PNG from an automatic viewpoint"),
    "robot-info": ("twinbench.commands.robot_info", "RobotInfoConfig", "main",
                   "links, joints and home end-effector pose of a robot (built-in arm or URDF)"),
    "eval": ("twinbench.commands.eval", "EvalConfig", "main",
             "evaluate policies on a task (parallel, resumable)"),
    "replay": ("twinbench.commands.replay", "ReplayConfig", "main",
               "replay recorded real rollouts open-loop in the twin"),
    "import-real": ("twinbench.commands.import_real", "ImportRealConfig", "main",
                    "import real-robot episode outcomes from a CSV into the results store"),
    "report": ("twinbench.commands.report", "ReportConfig", "main",
               "write a self-contained HTML report of an evaluation run"),
    "serve": ("twinbench.commands.serve", "ServeConfig", "main",
              "serve a local policy of a task over websocket (openpi's protocol) for remote: specs"),
    "sysid": ("twinbench.commands.sysid", "SysIdConfig", "main",
              "fit an object's physics to observed motion"),
    "segment": ("twinbench.commands.segment", "SegmentConfig", "main",
                "split a workcell scan into robot / background / objects with crop boxes"),
    "align-robot": ("twinbench.commands.align_robot", "AlignRobotConfig", "main",
                    "register robot Gaussians to the URDF (RANSAC + ICP) and label them by link"),
    "align-color": ("twinbench.commands.align_color", "AlignColorConfig", "main",
                    "fit the rendered -> real colour map (IRLS) and apply it to Gaussians"),
    "refine-cameras": ("twinbench.commands.refine_cameras", "RefineCamerasConfig", "main",
                       "correct static cameras' pose and intrinsics against their real images of the scan"),
    "import-phystwin": ("twinbench.commands.import_phystwin", "ImportPhysTwinConfig", "main",
                        "import a trained PhysTwin case as a twin object (restricted loader)"),
    "export-phystwin": ("twinbench.commands.export_phystwin", "ExportPhysTwinConfig", "main",
                        "write an imported PhysTwin object back as a PhysTwin case"),
    "mesh-to-object": ("twinbench.commands.mesh_to_object", "MeshToObjectConfig", "main",
                       "a rigid spring-mass object with surface Gaussians from a closed mesh"),
    "study": ("twinbench.commands.study", "StudyCommand", "main",
              "sim-vs-real study on a hidden real workcell "
              "(make-real|evidence|reconstruct|evaluate|run|combine)"),
}


def _usage() -> str:
    lines = ["usage: twinbench <command> [--help] [--debug] [options]", "",
             "--debug: show the full traceback of an error (else one line; exit code 2 for bad input)", "",
             "commands:"]
    lines += [f"  {name:<14} {doc}" for name, (_, _, _, doc) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import tyro

    argv = list(sys.argv[1:] if argv is None else argv)
    debug = "--debug" in argv or os.environ.get("TWINBENCH_DEBUG", "") not in ("", "0")
    argv = [a for a in argv if a != "--debug"]
    if not argv or argv[0] in ("-h", "--help"):
        print(_usage())
        return 0
    name, rest = argv[0], argv[1:]
    if name not in COMMANDS:
        print(f"twinbench: unknown command {name!r}\n\n{_usage()}", file=sys.stderr)
        return 2
    module_name, config_name, func_name, _ = COMMANDS[name]
    quiet_warp()  # no Warp banner or per-module load lines in the command's output
    module = importlib.import_module(module_name)
    config = tyro.cli(getattr(module, config_name), args=rest, prog=f"twinbench {name}")
    if debug:
        return int(getattr(module, func_name)(config) or 0)
    try:
        return int(getattr(module, func_name)(config) or 0)
    except BaseException as err:  # noqa: BLE001 - reported as one line below, re-raised when not ours
        return _report_error(name, err)


# ---- errors: one line on stderr, exit code 2 for bad input ------------------------------------------
# Bad input: the project's InputError (GaussianFileError, URDFError, ...) and what reading a user's file
# or argument raises. Anything else is a bug: one line too (exit 1), the traceback with --debug.
_BAD_INPUT = (ValueError, KeyError, FileNotFoundError, FileExistsError, NotADirectoryError, IsADirectoryError,
              PermissionError, ImportError)


def _error_message(err: BaseException) -> str:
    if isinstance(err, KeyError) and len(err.args) == 1 and isinstance(err.args[0], str):
        text = err.args[0]  # str(KeyError) adds quotes
    else:
        text = str(err) or type(err).__name__
    return text.strip()


def _report_error(command: str, err: BaseException) -> int:
    """Print `err` for a person (no traceback) and return the exit code; re-raises SystemExit."""
    if isinstance(err, SystemExit):
        raise err
    if isinstance(err, KeyboardInterrupt):
        print(f"twinbench {command}: interrupted", file=sys.stderr)
        return 130
    if isinstance(err, _BAD_INPUT):
        print(f"twinbench {command}: error: {_error_message(err)}", file=sys.stderr)
        return 2
    if isinstance(err, OSError):  # the machine failed (disk full, ...), not the input
        text = _error_message(err)
        if err.errno == errno.ENOSPC and err.filename is not None:
            from twinbench.errors import free_space

            text += f" ({free_space(err.filename)}); free space there and run the same command again"
        print(f"twinbench {command}: error: {type(err).__name__}: {text}", file=sys.stderr)
        return 1
    print(f"twinbench {command}: internal error: {type(err).__name__}: {_error_message(err)} "
          "(re-run with --debug for the traceback, and please report it)", file=sys.stderr)
    return 1


if __name__ == "__main__":
    sys.exit(main())
