"""twinbench.scene."""
