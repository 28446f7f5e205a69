"""twinbench.robot: URDF model + FK/IK, velocity-control mimic controller, robot Gaussians, built-in arm."""

from twinbench.robot.builtin import load_builtin_arm, load_xarm7
from twinbench.robot.controller import ControllerConfig, ControllerState, RobotCommand, RobotController
from twinbench.robot.gaussians import RobotGaussians, sample_robot_scan
from twinbench.robot.ik import IKResult, solve_ik
from twinbench.robot.model import RobotModel, URDFError, load_robot

__all__ = [
    "ControllerConfig",
    "ControllerState",
    "IKResult",
    "RobotCommand",
    "RobotController",
    "RobotGaussians",
    "RobotModel",
    "URDFError",
    "load_builtin_arm",
    "load_robot",
    "load_xarm7",
    "sample_robot_scan",
    "solve_ik",
]
