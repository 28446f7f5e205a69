"""twinbench.policies: the policy protocol, scripted/degraded experts, remote and LeRobot policies."""

from twinbench.policies.base import ChunkedPolicy, Policy, PolicyError
from twinbench.policies.degraded import DegradedPolicy, level_to_train_step
from twinbench.policies.spec import PolicySpec, make_policy, parse_policy_spec

__all__ = [
    "ChunkedPolicy", "DegradedPolicy", "Policy", "PolicyError", "PolicySpec", "level_to_train_step",
    "make_policy", "parse_policy_spec",
]
