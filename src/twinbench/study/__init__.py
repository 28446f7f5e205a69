"""twinbench.study (issue #24): predictive validity measured on a hidden "real" workcell.

- `real.make_real(task, seed, out, size)`: the real workcell (a twin directory) and its hidden values;
- `evidence.make_evidence(real, out, seed, size)`: what a user would have of it (scan, boxes, calibration,
  paired images, tracked motion), in the construction tools' formats;
- `reconstruct.reconstruct(evidence, out, variants)`: twins rebuilt from the evidence through the public
  CLI (segment -> align-robot -> align-color -> sysid -> twin build) and its ablations;
- policies, evaluation and the report: `policies`, `evaluate`, `run` (`twinbench study run`).

Tasks: push-t and rope-routing end to end; the rope's clip (a fixed collider) is segmented from the scan and
rebuilt as a collider of the twin, and its perception controller plans from the rope seen in the front image.
"""
