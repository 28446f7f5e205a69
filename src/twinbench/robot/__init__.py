"""twinbench.robot."""
