"""twinbench.evaluation."""
