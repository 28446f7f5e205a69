"""twinbench.physics."""
