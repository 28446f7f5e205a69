"""twinbench.policies."""
