"""twinbench.policies: the policy protocol, policy kinds (a registry: scripted/degraded experts, remote and
LeRobot policies, plugins' kinds), the wire protocol and policy I/O presets."""

from twinbench.policies.base import ChunkedPolicy, Policy, PolicyError
from twinbench.policies.degraded import DegradedPolicy, level_to_train_step
from twinbench.policies.spec import (
    PolicyKind,
    PolicySpec,
    make_policy,
    parse_policy_spec,
    register_policy_kind,
)

__all__ = [
    "ChunkedPolicy", "DegradedPolicy", "Policy", "PolicyError", "PolicyKind", "PolicySpec",
    "level_to_train_step", "make_policy", "parse_policy_spec", "register_policy_kind",
]
