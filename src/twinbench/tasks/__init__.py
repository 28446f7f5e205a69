"""twinbench.tasks."""
