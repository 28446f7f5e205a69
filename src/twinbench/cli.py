"""`twinbench <command>`: one typed (tyro) config per command, modules imported lazily."""

from __future__ import annotations

import importlib
import sys

# command -> (module, config dataclass, function taking the config)
COMMANDS: dict[str, tuple[str, str, str, str]] = {
    "demo": ("twinbench.demo", "DemoConfig", "main", "evaluate push-T policies on the built-in twin (CPU)"),
    "twin": ("twinbench.twin.cli", "TwinCommand", "main",
             "twin export (a task's built-in twin as a directory) | twin show (summary + camera PNGs)"),
    "physics-demo": ("twinbench.physics.demo", "DemoConfig", "main", "soft cube dropped, grasped and lifted"),
    "render-ply": ("twinbench.gaussians.cli", "RenderPlyConfig", "main",
                   "render a 3DGS .ply/.splat/.spz to a PNG from an automatic viewpoint"),
    "robot-info": ("twinbench.robot.info", "RobotInfoConfig", "robot_info",
                   "links, joints and home end-effector pose of a robot (built-in arm or URDF)"),
    "eval": ("twinbench.evaluation.runner", "EvalConfig", "main",
             "evaluate policies on a task (parallel, resumable)"),
    "replay": ("twinbench.evaluation.replay", "ReplayConfig", "main",
               "replay recorded real rollouts open-loop in the twin"),
    "import-real": ("twinbench.evaluation.real", "ImportRealConfig", "main",
                    "import real-robot episode outcomes from a CSV into the results store"),
    "report": ("twinbench.evaluation.report", "ReportConfig", "main",
               "write a self-contained HTML report of an evaluation run"),
}


def quiet_warp() -> None:
    """Keep Warp's init banner and per-module load lines out of stdout (warnings still show): Warp >= 1.19
    reads `config.log_level`; older releases read `config.quiet`."""
    import warp as wp

    if hasattr(wp.config, "log_level") and hasattr(wp, "LOG_WARNING"):
        wp.config.log_level = wp.LOG_WARNING
    else:
        wp.config.quiet = True


def _usage() -> str:
    lines = ["usage: twinbench <command> [--help] [options]", "", "commands:"]
    lines += [f"  {name:<14} {doc}" for name, (_, _, _, doc) in COMMANDS.items()]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    import tyro

    argv = list(sys.argv[1:] if argv is None else argv)
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
    result = getattr(module, func_name)(config)
    return int(result or 0)


if __name__ == "__main__":
    sys.exit(main())
