"""twinbench.gaussians."""
